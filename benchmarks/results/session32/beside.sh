#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~15 min:
# 1. the GPU tests of the hybrid chain solve (its partition test now on the GPU: the short lease's pytest process
#    crashed with the test on Warp's CPU fibers), the block and partitioned solves, and the rods / cloth, whose serial
#    walk now loads each node and constraint once (bit-identical on the CPU);
# 2. that serial walk against the code before it (/tmp/old = d4fe1b9 with its own benchmark scripts, same call):
#    RopeCutting, PrecisionCutting, TissueDissection STATE and RGB 64x64 (198.7k with the expert: #17 needs 200k), the
#    free cloth and a rod in physics alone; ThreadInHole (its per-vertex tet solve, 60 % of its step, no longer keeps
#    Dm^-1 in local memory);
# 3. the hybrid solve against the packed PCR one on the same GPU (the short lease timed only the hybrid, on an H100):
#    the rod, RopeThreading and LigatingLoop (their default is "pcr"), at 4 and 8 rows per lane; RopeCutting (its five
#    ropes of 20 rows in one warp per env at 4 rows per lane; the serial walk has 5 threads per env, the PCR packs lost);
# 4. TissueDissection RGB with the expert's actions replayed (the step alone, #17's regime) beside the expert timed;
# 5. PickAndPlace's expert on its new GPU default (the packed block solve), 256 first episodes;
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session32
out=/tmp/r/beside32
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_chains_hybrid.py tests/test_chains_block.py \
  tests/test_chains_partitioned.py tests/test_physics_rods.py tests/test_physics_deformables.py --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
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
    bench rc_$code $code RopeCutting STATE --policy expert
    bench pc_$code $code PrecisionCutting STATE --policy expert
    bench td_state_$code $code TissueDissection STATE --policy expert
    bench td_rgb_$code $code TissueDissection RGB --policy expert
    bench tih_$code $code ThreadInHole STATE --policy expert
  done
  for code in old new; do
    path=$new; script=benchmarks/bench_physics.py
    if [ "$code" = old ]; then path=$old; script=/tmp/old/benchmarks/bench_physics.py; fi
    PYTHONPATH=$path python3 "$script" --device "$dev" --num-envs "$n" --scene rod cloth_free --steps 20 \
      --settle-steps 5 --out "$out/physics_$code.jsonl" > "$out/physics_$code.txt" 2>&1
    echo "physics_$code rc=$?"; grep "env-steps/s" "$out/physics_$code.txt"
  done
fi
PYTHONPATH=$new python3 benchmarks/bench_physics.py --device "$dev" --num-envs "$n" --scene rod cloth_free \
  --chain-solver pcr hybrid --lane-rows 4 8 --steps 20 --settle-steps 5 --out "$out/physics_block.jsonl" \
  > "$out/physics_block.txt" 2>&1
echo "physics_block rc=$?"; grep "env-steps/s" "$out/physics_block.txt"
bench rc_hybrid4 new RopeCutting STATE --policy expert --set chain_solver=hybrid --lane-rows 4
bench rc_hybrid8 new RopeCutting STATE --policy expert --set chain_solver=hybrid --lane-rows 8
bench rt_pcr new RopeThreading STATE --policy expert
bench rt_hybrid4 new RopeThreading STATE --policy expert --set chain_solver=hybrid --lane-rows 4
bench ll_pcr new LigatingLoop STATE --policy expert
bench ll_hybrid4 new LigatingLoop STATE --policy expert --set chain_solver=hybrid --lane-rows 4
bench td_rgb_replay new TissueDissection RGB --policy replay --replay-steps 200
bench td_rgb_expert new TissueDissection RGB --policy expert
PYTHONPATH=$new python3 benchmarks/expert_success.py --task PickAndPlace --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS --out "$out/expert_pp.jsonl" > "$out/expert_pp.txt" 2>&1
echo "expert_pp rc=$? $(tail -1 "$out/expert_pp.txt" | cut -c1-260)"
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
