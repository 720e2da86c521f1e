#!/usr/bin/env bash
# The forty-first session's lease on one H200 (only `nvidia-h200` was lent), run as queue.sh's BESIDE with an empty
# queue (the queue exits at once; this script then has the GPU alone), in order of need, each item skipped once
# DEADLINE (s, default 1020) has passed:
# 1. GPU tests of the fortieth session's changes (the clustered surface query, bench_env --surface-leaf-size);
# 2. the step of the six tasks whose #17 / #18 targets are open (expert, 4,096 envs), then their RGB 64x64 steps
#    (#17 / #18 ask >= 200k each; none measured since the thirtieth session: TissueDissection 193.9k then);
# 3. profiles after 20 warm-up steps of PrecisionCutting (26.3k, target 100k), RopeCutting (327k, 500k) and
#    ThreadInHole (203k, 300k) on the current code: where the CPU work of the session goes;
# 4. the cull groups (a body's shapes culled by one bounding sphere first) against 668d57e (.device/small/old) on
#    RopeCutting, TissueDissection and RopeThreading (the old code at the new default cap, 128);
# 5. RopeThreading's hybrid chain solve at 112 / 144 registers (128: 156.8k); collide_particles at 64 registers
#    (LigatingLoop, RopeThreading, RopeCutting); the surfaces' leaf size 4 / 16 against 8 (LigatingLoop, ThreadInHole);
# 6. GraspLiftAndTouch's continuous expert in its six configurations on the clustered surface query;
# 7. 10^7-step random-action soaks of LigatingLoop and ThreadInHole on it (the #18 fault bar);
# 8. the learning queue JOBS (ThreadInHole normal with normalised observations, a fourth seed) with the time left.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:0}
n=${NUM_ENVS:-4096}
deadline=${DEADLINE:-1020}
d=benchmarks/results/session41
out=/tmp/r/beside41
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old  # 668d57e's lapwarp, for bench_old
. train/device/beside_lib.sh  # bench, bench_old, run_queue
in_time() { [ $(( $(date +%s) - t0 )) -lt "$deadline" ] || { echo "deadline: skipped $*"; return 1; }; }
PYTHONPATH=$new timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py \
  tests/test_train_and_bench.py -k "clustered or surface or leaf or contact_settings" --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
for task in PrecisionCutting RopeCutting TissueDissection ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
for task in TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop PrecisionCutting; do
  in_time "rgb_$task" && bench "rgb_$task" "$task" expert --obs RGB
done
echo "benches done at $(( $(date +%s) - t0 )) s"
for task in PrecisionCutting RopeCutting ThreadInHole; do
  in_time "profile_$task" || continue
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task "$task" --device "$dev" --num-envs "$n" \
    --steps 5 --warmup 20 --top 30 --out "$out/profile_$task.json" > "$out/profile_$task.txt" 2>&1
  echo "profile_$task rc=$? $(head -2 "$out/profile_$task.txt" | tr '\n' ' ' | cut -c1-300)"
done
in_time old && bench_old step_old_RopeCutting RopeCutting expert
in_time old && bench_old step_old_TissueDissection TissueDissection expert
in_time old && bench_old rt_old_cap128 RopeThreading expert --max-registers solve_chains_hybrid=128
for cap in 112 144; do
  in_time "rt_cap$cap" && bench "rt_cap$cap" RopeThreading expert --max-registers solve_chains_hybrid="$cap"
done
for task in LigatingLoop RopeThreading RopeCutting; do
  in_time "pcap64_$task" && bench "pcap64_$task" "$task" expert --max-registers collide_particles=64
done
for task in LigatingLoop ThreadInHole; do
  for k in 4 16; do
    in_time "leaf${k}_$task" && bench "leaf${k}_$task" "$task" expert --surface-leaf-size "$k"
  done
done
echo "checks done at $(( $(date +%s) - t0 )) s"
if in_time expert_glt; then
  PYTHONPATH=$new timeout 240 python3 benchmarks/expert_success.py --task GraspLiftAndTouch --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --config end_in_phase=LIFT --config end_in_phase=TOUCH \
    --config end_in_phase=DONE --config start_in_phase=LIFT end_in_phase=TOUCH \
    --config start_in_phase=LIFT end_in_phase=DONE --config start_in_phase=TOUCH end_in_phase=DONE \
    --out "$out/expert_glt.jsonl" > "$out/expert_glt.txt" 2>&1
  echo "expert_glt rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_glt.jsonl" | tr '\n' ' ')"
fi
for task in LigatingLoop ThreadInHole; do
  in_time "soak_$task" || continue
  PYTHONPATH=$new timeout 240 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
    --tasks "$task" --action-types CONTINUOUS --out "$out/soak_$task.jsonl" > "$out/soak_$task.txt" 2>&1
  echo "soak_$task rc=$? $(tail -1 "$out/soak_$task.txt" | cut -c1-300)"
done
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/jobs_beside.txt}" "${QUEUE_DEADLINE:-1080}"
