#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1),
# written in the thirty-ninth session, in order of need (~15 min), then the learning queue JOBS until DEADLINE:
# 1. GPU tests of the thirty-ninth session's changes (the chain kernels without loop / cut branches, the surface refit
#    per env step, the vertex solve's start in the prediction);
# 2. LigatingLoop's state-dependent surface contact (4.2 ms per env step at steps 10-15 after reset, 20.8 at 60-65
#    with the refit once per env step): its profile at steps 60-65 on its default (a refit every physics step), the
#    refit every 10 / 5 / 4 substeps within a physics step (more refits, smaller drift), and the contact kernel at 64
#    registers (80 now: three 256-thread blocks per SM);
# 3. ThreadInHole with its surface contact at 64 registers and its refit every 5 physics steps (10 now);
# 4. RopeThreading's hybrid chain kernel at 2 rows per lane (168 registers) and capped at 168 / 128;
# 5. the step of the six tasks whose #17 / #18 targets are open, same call (expert, 4,096 envs).
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3_next.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session39
out=/tmp/r/beside40
mkdir -p "$out"
new=/tmp/site:$PWD
. train/device/beside_lib.sh  # bench, run_queue
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_chains_block.py tests/test_chains_hybrid.py \
  tests/test_contact.py tests/test_fused_tets.py -k "long_rope or rods_match or stale_surface or surface_refit or start_in_the_prediction" \
  --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
PYTHONPATH=$new timeout 240 python3 benchmarks/profile_step.py --task LigatingLoop --device "$dev" --num-envs "$n" \
  --steps 5 --warmup 60 --top 30 --out "$out/profile_ll_w60.json" > "$out/profile_ll_w60.txt" 2>&1
echo "profile_ll_w60 rc=$? $(head -2 "$out/profile_ll_w60.txt" | tr '\n' ' ' | cut -c1-300)"
bench ll LigatingLoop expert
for k in 10 5 4; do
  bench "ll_int$k" LigatingLoop expert --surface-refit-interval "$k"
done
bench ll_surf64 LigatingLoop expert --max-registers collide_surface=64
bench tih ThreadInHole expert
bench tih_surf64 ThreadInHole expert --max-registers collide_surface=64
bench tih_steps5 ThreadInHole expert --surface-refit-steps 5
bench rt RopeThreading expert
bench rt_rows2 RopeThreading expert --lane-rows 2
bench rt_cap168 RopeThreading expert --max-registers solve_chains_hybrid=168
bench rt_cap128 RopeThreading expert --max-registers solve_chains_hybrid=128
for task in RopeCutting PrecisionCutting TissueDissection; do
  bench "step_$task" "$task" expert
done
run_queue "${JOBS:-$d/next_jobs_gpu3_next.txt}" "${DEADLINE:-1400}"
