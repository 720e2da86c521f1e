#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-sixth session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0), short so that the learning queue gets most of the lease, each item skipped once DEADLINE (s,
# default 450) has passed:
# 0. ContactSystem.surface_bounds "fused" (a deforming surface's leaf and super-leaf boxes in one launch, a block per
#    env) against the two launches ("separate", the default): ThreadInHole (0.95 ms per env step in the two launches;
#    50 leaves: 64 / 32 lanes) and LigatingLoop (2.24 ms; 188 leaves: 64 / 128 / 256 lanes); and ContactSystem.
#    report_forces off (no per-contact atomic add into report_force, which no task reads) on ThreadInHole,
#    LigatingLoop and RopeThreading (its rope lies on the floor: ~100 contacts per env and sweep on one address);
# 1. ThreadInHole's and RopeThreading's RGB 64x64 steps with those settings (#18's 200k: 198.3k / 184.7k);
# 2. GPU tests of the contact system's surfaces and forces (one round: the H200's same-call spread is ~0.05 %);
# then the learning queue JOBS (next_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1650).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench, run_queue
DEADLINE=${DEADLINE:-450} beside_init /tmp/r/beside47
d=benchmarks/results/session46
for round in a; do
  in_time "round_$round" || continue
  bench "tih_sep_$round" ThreadInHole expert --surface-bounds separate
  bench "tih_f64_$round" ThreadInHole expert --surface-bounds fused --surface-bounds-lanes 64
  [ "$round" = a ] && bench tih_f32_a ThreadInHole expert --surface-bounds fused --surface-bounds-lanes 32
  bench "tih_noforce_$round" ThreadInHole expert --contact-forces off
  bench "ll_sep_$round" LigatingLoop expert --surface-bounds separate
  [ "$round" = a ] && bench ll_f64_a LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 64
  bench "ll_f128_$round" LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 128
  [ "$round" = a ] && bench ll_f256_a LigatingLoop expert --surface-bounds fused --surface-bounds-lanes 256
  bench "ll_noforce_$round" LigatingLoop expert --contact-forces off
  bench "rt_$round" RopeThreading expert
  bench "rt_noforce_$round" RopeThreading expert --contact-forces off
  if [ "$round" = a ]; then
    in_time rgb && {
      bench rgb_tih ThreadInHole expert --obs RGB
      bench rgb_tih_f64_noforce ThreadInHole expert --obs RGB --surface-bounds fused --surface-bounds-lanes 64 \
        --contact-forces off
      bench rgb_rt RopeThreading expert --obs RGB
      bench rgb_rt_noforce RopeThreading expert --obs RGB --contact-forces off
    }
    if in_time pytest; then
      PYTHONPATH=$new timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py \
        -k "surface or forces" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
      echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
    fi
  fi
done
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1650}"
