#!/usr/bin/env bash
# GPU 3 of the next x4 lease (GPU 1 of an x2 lease: DEVICE=cuda:1), from the code copy (queue.sh's BESIDE), ~6 min:
# 1. the GPU tests of the triangle sweeps (the default is "auto" since the twenty-ninth session: the outcode sweep
#    where its window fits shared memory; "outcodes_skip" is new: bit-identical on the CPU);
# 2. the STATE steps at the new defaults (expert, 4,096 envs) against "outcodes_skip" in the same call:
#    TissueDissection (outcodes: 200.6k against the fused 192.0k, twenty-ninth session; no triangle past the cull in
#    54 % of its expert's env-steps, CPU), PrecisionCutting, GraspLiftAndTouch (also fused, its figure on record);
#    TissueDissection's RGB 64x64 step (176.1k with outcodes; the target is 200k); RopeCutting at 4 Newton steps
#    (244.1k against 189.6k at 6); ThreadInHole;
# 3. the skip sweep capped at 96 registers (the fused sweep gained 2.8 % capped at 96), STATE and RGB;
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session29
out=/tmp/r/beside29
mkdir -p "$out"
python3 -m pytest -q -p no:cacheprovider tests/test_contact.py -k "sweep or outcode" --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME TASK OBS [bench_env.py options...]
  local name=$1 task=$2 obs=$3
  shift 3
  python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 --obs "$obs" \
    --policy expert "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
# the new defaults (outcode sweep under "auto", 4 Newton steps) and the new exact sweep "outcodes_skip" (each env's
# sweep starts at its first triangle past the cull; an env with none is skipped) against "auto" in the same call
for task in TissueDissection PrecisionCutting GraspLiftAndTouch; do
  bench "default_$task" $task STATE
  bench "skip_$task" $task STATE --triangle-sweep outcodes_skip
done
bench fused_GraspLiftAndTouch GraspLiftAndTouch STATE --triangle-sweep fused
bench default_td_rgb TissueDissection RGB
bench skip_td_rgb TissueDissection RGB --triangle-sweep outcodes_skip
bench default_RopeCutting RopeCutting STATE
bench default_ThreadInHole ThreadInHole STATE
# a register cap of the outcode sweep (the fused sweep gained 2.8 % capped at 96; no "=" in the file names: the device
# tool returns plain names only)
bench caps_td_skip_96 TissueDissection STATE --triangle-sweep outcodes_skip --max-registers collide_triangle_outcodes=96
bench caps_td_rgb_skip_96 TissueDissection RGB --triangle-sweep outcodes_skip --max-registers collide_triangle_outcodes=96
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
