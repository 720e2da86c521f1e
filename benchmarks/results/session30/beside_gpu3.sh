#!/usr/bin/env bash
# GPU 3 of the next x4 lease (GPU 1 of an x2 lease: DEVICE=cuda:1), from the code copy (queue.sh's BESIDE), ~16 min:
# 1. the GPU tests of triangle contact on cut tet meshes (a cuttable tet mesh collides through its distinct faces
#    since the thirtieth session: TissueDissection's flap 658 triangles in 28 colours instead of 1,080 in 46);
# 2. TissueDissection's step (expert, 4,096 envs, STATE and RGB 64x64) with the code before that change and the
#    thread-per-slot attachments (6260a14's lapwarp, copied to /tmp/old by the install call from .device/small/old)
#    and after them, alternating old / new twice in this one call (twenty-ninth session: 200.3k STATE, 175.9k RGB;
#    the targets are 200k each);
# 3. PrecisionCutting at its new default 12 substeps x 1 Newton step against the 8 x 2 before (same code);
# 3b. the new block (PCR) chain solve (World.chain_solver="pcr", kernels/chains_block.py): its GPU tests, then the steps of
#    RopeCutting, PrecisionCutting, RopeThreading and LigatingLoop with it against their defaults (~4 min);
# 4. PrecisionCutting's scripted experts at 12 x 1 on 256 first episodes per configuration (~2 min);
# 5. TissueDissection's kernel profile with the new faces (the triangle contact was 7.28 ms of 21.13, H200);
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session30
out=/tmp/r/beside30
mkdir -p "$out"
python3 -m pytest -q -p no:cacheprovider tests/test_cutting_contact.py tests/test_contact.py -k "cut or sweep or outcode or tunnel" \
  --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
# the block (PCR) chain solve's GPU tests: blocks of many lanes (the CPU runs one), so its barriers are tested here
python3 -m pytest -q -p no:cacheprovider tests/test_chains_block.py tests/test_chains_partitioned.py --device "$dev" \
  > "$out/pytest_chains_cuda.txt" 2>&1
pcr_ok=$?
echo "pytest chains rc=$pcr_ok $(tail -1 "$out/pytest_chains_cuda.txt")"
bench() {  # NAME PYTHONPATH TASK OBS [bench_env.py options...]
  local name=$1 path=$2 task=$3 obs=$4
  shift 4
  PYTHONPATH=$path python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs "$obs" --policy expert "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
if [ -d /tmp/old/lapwarp ]; then
  for rep in 1; do  # the expected change is ~15-20 %, the run-to-run noise ~1-2 %
    bench "td_state_old_$rep" "$old" TissueDissection STATE
    bench "td_state_new_$rep" "$new" TissueDissection STATE
    bench "td_rgb_old_$rep" "$old" TissueDissection RGB
    bench "td_rgb_new_$rep" "$new" TissueDissection RGB
  done
else
  echo "no /tmp/old/lapwarp: the new code alone"
  bench td_state_new_1 "$new" TissueDissection STATE
  bench td_rgb_new_1 "$new" TissueDissection RGB
fi
bench pc_12x1 "$new" PrecisionCutting STATE
bench pc_8x2 "$new" PrecisionCutting STATE --set physics_substeps=8 cloth_newton_steps=2
# the block (PCR) chain solve against each task's default (one thread per chain; RopeThreading and LigatingLoop blocks
# of 8 links, kernels/chains_partitioned.py), where the chain solve leads the profile: RopeCutting (63 % at 6 Newton
# steps), PrecisionCutting's cloth (~80 %), RopeThreading's rope (~27 of 49 ms), LigatingLoop's loop; only if its GPU
# tests passed
if [ "$pcr_ok" -eq 0 ]; then
  for task in RopeCutting PrecisionCutting RopeThreading LigatingLoop; do
    bench "chains_default_$task" "$new" $task STATE
    bench "chains_pcr_$task" "$new" $task STATE --set chain_solver=pcr
  done
  # physics alone (bench_physics.py, 4,096 envs, 20 substeps): a hanging 100-segment rod and the free 40 x 40 cloth
  # (PrecisionCutting's grid), one thread per chain against the block solve (the partitioned solve is RopeThreading's
  # and LigatingLoop's default above)
  PYTHONPATH=$new python3 benchmarks/bench_physics.py --device "$dev" --num-envs "$n" --scene rod cloth_free \
    --chain-solver thomas pcr --out "$out/physics_chains.jsonl" > "$out/physics_chains.txt" 2>&1
  echo "physics_chains rc=$?"; grep "env-steps/s" "$out/physics_chains.txt"
  # where RopeCutting's and RopeThreading's steps go with it (RopeCutting: 63 % in the chain solve at 6 Newton steps)
  for task in RopeCutting RopeThreading; do
    PYTHONPATH=$new python3 benchmarks/profile_step.py --task $task --device "$dev" --num-envs "$n" --steps 10 \
      --set chain_solver=pcr --out "$out/profile_pcr_$task.json" > "$out/profile_pcr_$task.txt" 2>&1
    echo "profile_pcr_$task rc=$? $(grep -m1 "kernel time per env step" "$out/profile_pcr_$task.txt")"
  done
fi
# PrecisionCutting's experts at the new default 12 x 1 (CPU: 16 / 16 first episodes in each configuration), 256 first
# episodes per configuration and action type (#17 asks >= 90 %; at 8 x 2 every one was >= 94.5 %, twenty-eighth session)
PYTHONPATH=$new python3 benchmarks/expert_success.py --task PrecisionCutting --device "$dev" --num-envs 256 \
  --config path_function=line --config path_function=line randomize_path=true --config path_function=sine \
  --config path_function=sine randomize_path=true --out "$out/pc_expert_12x1.jsonl" > "$out/pc_expert_12x1.txt" 2>&1
echo "pc_expert_12x1 rc=$? $(tail -8 "$out/pc_expert_12x1.txt" | tr '\n' ' ')"
PYTHONPATH=$new python3 benchmarks/profile_step.py --task TissueDissection --device "$dev" --num-envs "$n" --steps 10 --out "$out/td_profile_new.json" \
  > "$out/td_profile_new.txt" 2>&1
echo "td_profile_new rc=$? $(grep -m1 "kernel time per env step" "$out/td_profile_new.txt")"
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
