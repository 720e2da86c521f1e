#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-first session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0) or beside a learning queue on the last GPU of a larger machine, in order of need, each item
# skipped once DEADLINE (s, default 1000) has passed, then the learning queue JOBS with the time left:
# 0. the cull groups against their absence (--no-cull-groups, same code): RopeCutting, TissueDissection,
#    RopeThreading (RopeCutting 321.4k against 330.3k at 668d57e in one pair of runs of the forty-first session);
# 1. the per-tool triangle boxes (triangle_sweep="shape_codes") on the tasks that keep "auto": ThreadInHole and
#    GraspLiftAndTouch, same call (if both gain, "auto" can take them where a system has at most 5 shapes);
#    TissueDissection's RGB 64x64 step with them (211.8k before); PrecisionCutting's triangle sweep at 64 / 128
#    lanes and its three-walk chain solve at 80 / 64 registers;
# 2. the steps of the six #17 / #18 tasks on the current defaults (PrecisionCutting's three-walk chain solve and
#    per-tool boxes, the particle contact at 64 registers for LigatingLoop, RopeThreading, RopeCutting);
# 3. PrecisionCutting's profile on its new defaults, after 20 warm-up steps;
# 4. PrecisionCutting's experts (line / sine, fixed / random; 256 first episodes) on the three-walk solve (round-off
#    from the serial walk's; 8 / 8 per path on the CPU).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS (next_jobs_beside.txt), DEADLINE (1000) and QUEUE_DEADLINE (1100) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:0}
n=${NUM_ENVS:-4096}
deadline=${DEADLINE:-1000}
d=benchmarks/results/session41
out=/tmp/r/beside42
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
. train/device/beside_lib.sh  # bench, bench_old, run_queue
in_time() { [ $(( $(date +%s) - t0 )) -lt "$deadline" ] || { echo "deadline: skipped $*"; return 1; }; }
for task in RopeCutting TissueDissection RopeThreading; do
  in_time "groups_$task" || continue
  bench "groups_$task" "$task" expert
  bench "nogroups_$task" "$task" expert --no-cull-groups
done
for task in ThreadInHole GraspLiftAndTouch; do
  in_time "sc_$task" || continue
  bench "oc_$task" "$task" expert
  bench "sc_$task" "$task" expert --triangle-sweep shape_codes
done
in_time rgb_td && bench rgb_TissueDissection TissueDissection expert --obs RGB
# PrecisionCutting's triangle sweep (23.2 ms of its 162.3 ms step, 8 colours of ~380 triangles) in blocks of 64 /
# 128 lanes instead of 32: a third of the chunks (and their three barriers each) per colour at 128
for lanes in 64 128; do
  in_time "pc_tri$lanes" && bench "pc_tri$lanes" PrecisionCutting expert --triangle-block-threads "$lanes"
done
# its three-walk chain solve (its default, 96 registers and a 64 B spill frame, sm_90) at 80 / 64 registers (112 /
# 176 B frames): 768 / 1,024 threads per SM instead of 640 for a walk that waits on each link's loads
for cap in 80 64; do
  in_time "pc_open_cap$cap" && bench "pc_open_cap$cap" PrecisionCutting expert --max-registers solve_open_chains="$cap"
done
for task in PrecisionCutting TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
if in_time profile_pc; then
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task PrecisionCutting --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_PrecisionCutting.json" \
    > "$out/profile_PrecisionCutting.txt" 2>&1
  echo "profile_PrecisionCutting rc=$? $(head -3 "$out/profile_PrecisionCutting.txt" | tr '\n' ' ' | cut -c1-300)"
fi
if in_time expert_pc; then
  PYTHONPATH=$new timeout 300 python3 benchmarks/expert_success.py --task PrecisionCutting --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --config path_function=line --config path_function=sine \
    --config path_function=line randomize_path=true --config path_function=sine randomize_path=true \
    --out "$out/expert_pc.jsonl" > "$out/expert_pc.txt" 2>&1
  echo "expert_pc rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_pc.jsonl" | tr '\n' ' ')"
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1100}"
