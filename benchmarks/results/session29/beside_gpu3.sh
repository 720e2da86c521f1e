#!/usr/bin/env bash
# GPU 3 of the next x4 lease (GPU 1 of an x2 lease: DEVICE=cuda:1), from the code copy (queue.sh's BESIDE), ~5 min:
# 1. the GPU tests of the triangle sweeps (the default is "auto" since the twenty-ninth session: the outcode sweep
#    where its window fits shared memory);
# 2. the STATE steps at the new defaults (expert, 4,096 envs): TissueDissection (outcodes: 200.6k against the fused
#    192.0k, twenty-ninth session), RopeCutting (4 Newton steps: 244.1k against 189.6k at 6), PrecisionCutting,
#    ThreadInHole; TissueDissection's RGB 64x64 step (176.1k with outcodes; the target is 200k); GraspLiftAndTouch
#    with the auto (outcode) and the fused sweep;
# 3. register caps of the outcode sweep (the fused sweep gained 2.8 % capped at 96, twenty-ninth session), STATE and
#    RGB, each against the uncapped step above;
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
for task in TissueDissection RopeCutting PrecisionCutting ThreadInHole; do
  bench "default_$task" $task STATE
done
bench default_td_rgb TissueDissection RGB
# GraspLiftAndTouch takes the outcode sweep too under "auto" (bit-identical on the CPU; not timed on the GPU yet)
bench default_GraspLiftAndTouch GraspLiftAndTouch STATE
bench fused_GraspLiftAndTouch GraspLiftAndTouch STATE --triangle-sweep fused
for cap in 96 64; do  # no "=" in the file names (the device tool returns plain names only)
  bench "caps_td_outcodes_$cap" TissueDissection STATE --max-registers collide_triangle_outcodes=$cap
  bench "caps_td_rgb_outcodes_$cap" TissueDissection RGB --max-registers collide_triangle_outcodes=$cap
done
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
