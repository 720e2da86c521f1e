#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~13 min
# of benchmarks in order of need, then the learning queue JOBS until DEADLINE seconds after this script started:
# 1. the GPU tests not yet run there: the register solve's env test as changed in the thirty-fourth session (one env
#    step with the hook still), the contact tests with the mesh-free particle launch, the fused tets with the rotations
#    refreshed once per sweep, the colour packing;
# 2. the thirty-fourth session's code against 70ff287 (/tmp/old, with its own benchmark scripts), same call: every task
#    without a mesh shape now launches the particle contact without the mesh query (RopeThreading +4.6 %, RopeCutting
#    +2.4 % in the quick lease) and ThreadInHole refreshes its hole's rotations once per sweep (+14.9 %):
#    TissueDissection STATE / RGB (#17's RGB 200k: 201.6k replayed), LigatingLoop, PrecisionCutting, ThreadInHole,
#    RopeThreading; then ThreadInHole with the per-vertex rotations on the new layout (the split of its +14.9 %);
# 3. ThreadInHole's expert on its new default in the flexible and inverted configurations (the normal one: 256 / 256 in
#    the quick lease) and a 10^7-step random-action soak of it.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session34
out=/tmp/r/beside34
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py tests/test_contact.py \
  tests/test_fused_tets.py tests/test_colour_packing.py --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME CODE(new|old) TASK OBS [bench_env.py options...]
  local name=$1 code=$2 task=$3 obs=$4 path=$new script=benchmarks/bench_env.py
  shift 4
  if [ "$code" = old ]; then path=$old; script=/tmp/old/benchmarks/bench_env.py; fi
  PYTHONPATH=$path python3 "$script" --task "$task" --device "$dev" --num-envs "$n" --seconds 3 --obs "$obs" "$@" \
    --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
if [ -d /tmp/old/lapwarp ]; then
  for code in old new; do
    bench td_state_$code $code TissueDissection STATE --policy expert
    bench td_rgb_$code $code TissueDissection RGB --policy expert
    bench ll_$code $code LigatingLoop STATE --policy expert
    bench pc_$code $code PrecisionCutting STATE --policy expert
    bench tih_$code $code ThreadInHole STATE --policy expert
    bench rt_$code $code RopeThreading STATE --policy expert
  done
fi
bench tih_vertex new ThreadInHole STATE --policy expert --set hole_rotation_update='"vertex"'
PYTHONPATH=$new python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS --config configuration=flexible --config configuration=inverted \
  --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
echo "expert_tih rc=$? $(tail -2 "$out/expert_tih.txt" | tr '\n' ' ' | cut -c1-400)"
PYTHONPATH=$new python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks ThreadInHole --action-types CONTINUOUS --out "$out/soak.jsonl" > "$out/soak.txt" 2>&1
echo "soak rc=$? $(tail -2 "$out/soak.txt" | tr '\n' ' ' | cut -c1-300)"
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
