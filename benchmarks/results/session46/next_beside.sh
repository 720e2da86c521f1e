#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-sixth session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0), short so that the learning queue gets most of the lease (its first row ~1,200 s), each item
# skipped once DEADLINE (s, default 300) has passed:
# 0. ContactSystem.surface_bounds "fused" (a deforming surface's leaf and super-leaf boxes in one launch, a block per
#    env) against the two launches ("separate", the default): ThreadInHole (0.95 ms per env step in the two launches;
#    50 leaves: 64 / 32 lanes) and LigatingLoop (2.24 ms; 188 leaves: 64 / 128 / 256 lanes), alternated; ThreadInHole's
#    RGB 64x64 both ways (#18's 200k: 198.3k in the forty-sixth session);
# 1. GPU tests of the contact system's surfaces (the fused bounds with real blocks), then a second round of 0;
# then the learning queue JOBS (next_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1600).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench, run_queue
DEADLINE=${DEADLINE:-300} beside_init /tmp/r/beside47
d=benchmarks/results/session46
if in_time bounds_a; then
  bench tih_sep_a ThreadInHole expert --surface-bounds separate
  bench tih_f64_a ThreadInHole expert --surface-bounds fused --surface-bounds-lanes 64
  bench tih_f32_a ThreadInHole expert --surface-bounds fused --surface-bounds-lanes 32
  bench ll_sep_a LigatingLoop expert --surface-bounds separate
  bench ll_f64_a LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 64
  bench ll_f128_a LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 128
  bench ll_f256_a LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 256
fi
in_time rgb && bench rgb_tih_sep ThreadInHole expert --obs RGB --surface-bounds separate
in_time rgb_fused && bench rgb_tih_f64 ThreadInHole expert --obs RGB --surface-bounds fused --surface-bounds-lanes 64
if in_time pytest; then
  PYTHONPATH=$new timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py -k "surface" \
    --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
if in_time bounds_b; then
  bench tih_sep_b ThreadInHole expert --surface-bounds separate
  bench tih_f64_b ThreadInHole expert --surface-bounds fused --surface-bounds-lanes 64
  bench ll_sep_b LigatingLoop expert --surface-bounds separate
  bench ll_f128_b LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 128
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1600}"
