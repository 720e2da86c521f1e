#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1),
# written in the fortieth session, in order of need (~23 min), then the learning queue JOBS until DEADLINE:
# 1. GPU tests of the fortieth session's changes (the clustered surface query, bench_env --surface-leaf-size);
# 2. LigatingLoop's profile at steps 60-65 on the clustered query (16.79 ms of surface contact per env step there on
#    668d57e's drift-grown BVH queries) and at steps 10-15;
# 3. the surfaces' leaf size: 4 and 16 triangles against 8 (LigatingLoop, ThreadInHole, GraspLiftAndTouch);
# 4. RopeThreading's hybrid chain solve at 96 / 112 / 144 registers against its new default 128 (156.8k; 168:
#    148.0k; uncapped 217: 137.1k); the cull groups (a body's shapes culled by one bounding sphere first) against
#    668d57e (.device/small/old, carried) on RopeThreading (the old code at the same cap), RopeCutting and
#    TissueDissection;
#    the shape contact kernels capped (collide_particles 71 -> 64 registers: 4 blocks of 256 per SM instead of 3;
#    LigatingLoop's 750 cavity nodes, RopeThreading's rope, RopeCutting's ropes; RopeCutting's segment colours 96 -> 80);
# 5. 10^7-step random-action soaks of LigatingLoop and ThreadInHole on the clustered query (the #18 fault bar), and
#    GraspLiftAndTouch's continuous expert in its six configurations on it (its liver surface is queried the new way,
#    and a surface vertex counts in its contact average only where its weight is above 0; 100 % each before);
# 6. the step of the six tasks whose #17 / #18 targets are open, same call (expert, 4,096 envs);
# 7. last (cut off if the lease ends first), their RGB 64x64 steps: #17 / #18 ask >= 200k each and none was measured
#    since the thirtieth session (TissueDissection 193.9k then).
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3_next.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session40
out=/tmp/r/beside41
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old  # 668d57e's lapwarp, for bench_old
. train/device/beside_lib.sh  # bench, bench_old, run_queue
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_contact.py tests/test_train_and_bench.py \
  -k "clustered or surface or leaf or contact_settings" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
for w in 60 10; do
  PYTHONPATH=$new timeout 240 python3 benchmarks/profile_step.py --task LigatingLoop --device "$dev" --num-envs "$n" \
    --steps 5 --warmup "$w" --top 30 --out "$out/profile_ll_w$w.json" > "$out/profile_ll_w$w.txt" 2>&1
  echo "profile_ll_w$w rc=$? $(head -3 "$out/profile_ll_w$w.txt" | tr '\n' ' ' | cut -c1-300)"
done
for task in LigatingLoop ThreadInHole GraspLiftAndTouch; do
  bench "leaf8_$task" "$task" expert
  for k in 4 16; do
    bench "leaf${k}_$task" "$task" expert --surface-leaf-size "$k"
  done
done
bench rt RopeThreading expert
bench_old rt_old_cap128 RopeThreading expert --max-registers solve_chains_hybrid=128
for cap in 96 112 144; do
  bench "rt_cap$cap" RopeThreading expert --max-registers solve_chains_hybrid="$cap"
done
for task in LigatingLoop RopeThreading RopeCutting; do
  bench "pcap64_$task" "$task" expert --max-registers collide_particles=64
done
bench segcap80_RopeCutting RopeCutting expert --max-registers collide_segment_colors=80
for task in LigatingLoop ThreadInHole; do
  PYTHONPATH=$new timeout 300 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
    --tasks "$task" --action-types CONTINUOUS --out "$out/soak_$task.jsonl" > "$out/soak_$task.txt" 2>&1
  echo "soak_$task rc=$? $(tail -1 "$out/soak_$task.txt" | cut -c1-300)"
done
PYTHONPATH=$new timeout 300 python3 benchmarks/expert_success.py --task GraspLiftAndTouch --device "$dev" \
  --num-envs 256 --action-types CONTINUOUS --config end_in_phase=LIFT --config end_in_phase=TOUCH \
  --config end_in_phase=DONE --config start_in_phase=LIFT end_in_phase=TOUCH \
  --config start_in_phase=LIFT end_in_phase=DONE --config start_in_phase=TOUCH end_in_phase=DONE \
  --out "$out/expert_glt.jsonl" > "$out/expert_glt.txt" 2>&1
echo "expert_glt rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_glt.jsonl" | tr '\n' ' ')"
for task in RopeCutting PrecisionCutting TissueDissection; do
  bench "step_$task" "$task" expert
done
bench_old step_old_RopeCutting RopeCutting expert
bench_old step_old_TissueDissection TissueDissection expert
for task in TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop PrecisionCutting; do
  bench "rgb_$task" "$task" expert --obs RGB
done
run_queue "${JOBS:-$d/next_jobs_gpu3_next.txt}" "${DEADLINE:-1400}"
