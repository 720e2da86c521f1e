#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-third session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0) or beside a learning queue on the last GPU of a larger machine, in order of need, each item
# skipped once DEADLINE (s, default 1000) has passed, then the learning queue JOBS with the time left:
# 0. RopeThreading on its new defaults (199.8k in the forty-third session: #18's 200k), alternated with its closing
#    attachment pass at the end of the hybrid rope solve (--attach-in-rod-solve on: off until timed; if it gains, the
#    World's default) and register caps not tried yet: its particle contact at 56 / 48 (64), its fused
#    rod-and-prediction launch at 56 / 48 (64, 64 lanes), its hybrid chain solve at 96 (128); then its RGB 64x64 step
#    and profile;
# 1. RopeCutting's prediction in the rod launch with that launch capped at 64 registers like its solve_rods_fused (the
#    forty-third session timed it uncapped: 324.8k against 326.0k without), twice alternated;
# 2. a 10^6-step random-action soak of RopeThreading and RopeCutting on the new rod launch;
# 3. GPU tests of this session's kernels (the held segments, the prediction in the rod sweep, the bench flags);
# 4. the six #17 / #18 tasks' steps on the current defaults and ThreadInHole / LigatingLoop RGB 64x64.
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS (next_jobs_beside.txt), DEADLINE (1000) and QUEUE_DEADLINE (1100) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:0}
n=${NUM_ENVS:-4096}
deadline=${DEADLINE:-1000}
d=benchmarks/results/session43
out=/tmp/r/beside44
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
. train/device/beside_lib.sh  # bench, bench_old, run_queue
in_time() { [ $(( $(date +%s) - t0 )) -lt "$deadline" ] || { echo "deadline: skipped $*"; return 1; }; }
for round in a b; do
  in_time "rt_$round" || continue
  bench "rt_$round" RopeThreading expert
  bench "rt_attach_$round" RopeThreading expert --attach-in-rod-solve on
  bench "rt_cp56_$round" RopeThreading expert --max-registers collide_particles=56
  bench "rt_cp48_$round" RopeThreading expert --max-registers collide_particles=48
done
for cap in 56 48; do
  in_time "rt_rods$cap" && bench "rt_rods$cap" RopeThreading expert --max-registers predict_and_solve_rods_fused="$cap"
done
in_time rt_hybrid96 && bench rt_hybrid96 RopeThreading expert --max-registers solve_chains_hybrid=96
in_time rgb_rt && bench rgb_RopeThreading RopeThreading expert --obs RGB
if in_time profile_rt; then
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task RopeThreading --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_RopeThreading.json" \
    > "$out/profile_RopeThreading.txt" 2>&1
  echo "profile_RopeThreading rc=$? $(head -4 "$out/profile_RopeThreading.txt" | tr '\n' ' ' | cut -c1-400)"
fi
for round in a b; do
  in_time "rc_pred_$round" || continue
  bench "rc_$round" RopeCutting expert
  bench "rc_pred64_$round" RopeCutting expert --predict-in-rod-sweep on \
    --max-registers predict_and_solve_rods_fused=64
done
for task in RopeThreading RopeCutting; do
  if in_time "soak_$task"; then
    PYTHONPATH=$new timeout 200 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e6 \
      --tasks "$task" --action-types CONTINUOUS --out "$out/soak_$task.jsonl" > "$out/soak_$task.txt" 2>&1
    echo "soak_$task rc=$? $(tail -1 "$out/soak_$task.txt" | cut -c1-300)"
  fi
done
if in_time pytest; then
  PYTHONPATH=$new timeout 240 python3 -m pytest -q -p no:cacheprovider tests/test_physics_basic.py \
    tests/test_physics_deformables.py tests/test_grasping.py tests/test_pick_and_place.py tests/test_physics_rods.py \
    tests/test_chains_hybrid.py \
    -k "prediction or attachment or grasp or hold or fused" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
for task in PrecisionCutting TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
for task in ThreadInHole LigatingLoop; do
  in_time "rgb_$task" && bench "rgb_$task" "$task" expert --obs RGB
done
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1100}"
