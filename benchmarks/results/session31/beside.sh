#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~20 min:
# 1. the GPU tests of the block (PCR) chain solve since its packs (a family's open chains end to end in one block; laid
#    out outside the step since the thirty-first session's fix: a layout inside the env's captured first step replayed
#    garbage rows), of the fused velocity update + prediction, the fused rod sweep and segment contact colours, the
#    one-launch stability check
#    (a block-wide maximum on the GPU), the contact overflow sink and the distinct-slot inverse masses;
# 2. the chain solves per task, expert, 4,096 envs: RopeCutting serial / packs of 128 rows / a chain per block,
#    PrecisionCutting serial / packs, RopeThreading and LigatingLoop serial-or-partitioned / their new GPU default
#    "pcr" (set from the old per-chain kernel's 113.3k vs 96.9k and 74.5k vs 71.7k), PickAndPlace's default
#    (partitioned) / packs; the free cloth and a rod in physics alone; then the experts with the packs on the GPU
#    (the broken layout made PrecisionCutting's fail every episode while its step looked 2.4x faster);
# 3. the code before this session's step changes (7304414, /tmp/old: the velocity update fused into the next
#    substep's prediction, the rods' colours in one launch (also alone above: --rod-solver colored), the stability
#    check and restore in one launch, the contact reports' clear and overflow folded into other kernels, the
#    distinct-slot inverse masses; ~100 of TissueDissection's 498 launches per env step, ~200 of RopeCutting's 558)
#    against the new: TissueDissection STATE and RGB 64x64
#    (218.6k / 193.9k at 6260a14 + the thirtieth session's changes; RGB needs 200k), RopeCutting, ThreadInHole;
# 4. TissueDissection's kernel profile (RGB); 5. RopeThreading's and LigatingLoop's soaks with the block solve;
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session31
out=/tmp/r/beside31
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_chains_block.py tests/test_chains_partitioned.py \
  tests/test_physics_basic.py tests/test_physics_deformables.py tests/test_physics_rods.py tests/test_bad_input.py \
  tests/test_contact.py tests/test_instruments.py \
  -k "pcr or pack or partitioned or fused or distinct or restores or instability or overflow or rig" --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
pcr_ok=$?
echo "pytest rc=$pcr_ok $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME PYTHONPATH TASK OBS [bench_env.py options...]
  local name=$1 path=$2 task=$3 obs=$4
  shift 4
  PYTHONPATH=$path python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs "$obs" --policy expert "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
if [ "$pcr_ok" -eq 0 ]; then
  bench rc_thomas "$new" RopeCutting STATE --set chain_solver=thomas
  bench rc_pcr "$new" RopeCutting STATE --set chain_solver=pcr
  bench rc_pcr_chain "$new" RopeCutting STATE --set chain_solver=pcr --pcr-rows 1
  bench rc_rods_colored "$new" RopeCutting STATE --set chain_solver=thomas --rod-solver colored
  bench pc_thomas "$new" PrecisionCutting STATE --set chain_solver=thomas
  bench pc_pcr "$new" PrecisionCutting STATE --set chain_solver=pcr
  bench rt_thomas "$new" RopeThreading STATE --set chain_solver=thomas
  bench rt_auto "$new" RopeThreading STATE
  bench rt_rods_colored "$new" RopeThreading STATE --rod-solver colored
  bench ll_thomas "$new" LigatingLoop STATE --set chain_solver=thomas
  bench ll_auto "$new" LigatingLoop STATE
  bench pp_auto "$new" PickAndPlace STATE
  bench pp_pcr "$new" PickAndPlace STATE --set chain_solver=pcr
  PYTHONPATH=$new python3 benchmarks/bench_physics.py --device "$dev" --num-envs "$n" --scene rod cloth_free \
    --chain-solver thomas pcr --pcr-rows 0 1 --out "$out/physics_chains.jsonl" > "$out/physics_chains.txt" 2>&1
  echo "physics_chains rc=$?"; grep "env-steps/s" "$out/physics_chains.txt"
  # the experts with the packed block solve (first episodes; CPU: 4 / 4 each)
  for task in RopeCutting PrecisionCutting RopeThreading LigatingLoop; do
    PYTHONPATH=$new python3 benchmarks/expert_success.py --task $task --device "$dev" --num-envs 256 \
      --config chain_solver=pcr --action-types CONTINUOUS --out "$out/expert_pcr_$task.jsonl" \
      > "$out/expert_pcr_$task.txt" 2>&1
    echo "expert_pcr_$task rc=$? $(tail -1 "$out/expert_pcr_$task.txt" | cut -c1-260)"
  done
fi
if [ -d /tmp/old/lapwarp ]; then
  bench td_state_old "$old" TissueDissection STATE
  bench td_state_new "$new" TissueDissection STATE
  bench td_rgb_old "$old" TissueDissection RGB
  bench td_rgb_new "$new" TissueDissection RGB
  bench rc_old "$old" RopeCutting STATE --set chain_solver=thomas
  bench tih_old "$old" ThreadInHole STATE
  bench tih_new "$new" ThreadInHole STATE
fi
PYTHONPATH=$new python3 benchmarks/profile_step.py --task TissueDissection --device "$dev" --num-envs "$n" --steps 10 \
  --set observation_type=RGB --out "$out/td_rgb_profile.json" > "$out/td_rgb_profile.txt" 2>&1
echo "td_rgb_profile rc=$? $(grep -m1 "kernel time per env step" "$out/td_rgb_profile.txt")"
# RopeThreading and LigatingLoop on their new GPU default (the block chain solve): a random-action soak of 10^7
# env-steps each, continuous actions (~100 + ~140 s), if the packs' tests passed
if [ "$pcr_ok" -eq 0 ]; then
  PYTHONPATH=$new python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
    --tasks RopeThreading LigatingLoop --action-types CONTINUOUS --out "$out/soak_pcr.jsonl" > "$out/soak_pcr.txt" 2>&1
  echo "soak_pcr rc=$? $(tail -2 "$out/soak_pcr.txt" | tr '\n' ' ' | cut -c1-300)"
fi
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
