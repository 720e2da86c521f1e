#!/usr/bin/env bash
# The forty-seventh session's lease: the forty-sixth session's planned checks (its next_beside.sh) and a probe of the
# shading pass, run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0), each item skipped once DEADLINE (s, default 500) has passed, one round (the H200's same-call
# spread is ~0.05 %). Three contact options, each off by default until timed here:
# - surface_bounds "fused": a deforming surface's leaf and super-leaf boxes in one launch, a block per env, instead of
#   two (ThreadInHole 0.95 ms per env step in them, 50 leaves; LigatingLoop 2.24 ms, 188 leaves);
# - report_forces off: no per-contact atomic add into report_force, which no task reads (RopeThreading's rope on its
#   floor: ~100 contacts per env and sweep adding into one address);
# - defer_surface_deltas: a surface's averaged corrections applied by the next substep's prediction launch instead of
#   their own launch (ThreadInHole 3 of 4 per world step, LigatingLoop 19 of 20);
# 0. each alone and all together on ThreadInHole and LigatingLoop, forces off on RopeThreading;
# 1. ThreadInHole's and RopeThreading's RGB 64x64 steps with them (#18's 200k: 198.3k / 184.7k);
# 2. GPU tests of the contact system (the fused bounds with real blocks, forces off, the deferred deltas);
# then the learning queue JOBS (next_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1100).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench, run_queue
DEADLINE=${DEADLINE:-500} beside_init /tmp/r/beside47
d=benchmarks/results/session46
p=benchmarks/results/session47/probes
all="--contact-forces off --defer-surface-deltas on --surface-bounds fused --surface-bounds-lanes"
# each task's variants in one process (bench_variants: one start-up and compile for all): the default, the fused
# bounds at each lane count, forces off, deferred deltas, all three
in_time tih && bench_variants tih ThreadInHole expert "tih=" "tih_f64=--surface-bounds fused --surface-bounds-lanes 64" \
  "tih_noforce=--contact-forces off" "tih_defer=--defer-surface-deltas on" "tih_all=$all 64"
in_time ll && bench_variants ll LigatingLoop expert "ll=" "ll_f128=--surface-bounds fused --surface-bounds-lanes 128" \
  "ll_f64=--surface-bounds fused --surface-bounds-lanes 64" "ll_noforce=--contact-forces off" \
  "ll_defer=--defer-surface-deltas on" "ll_all=$all 128"
in_time rt && bench_variants rt RopeThreading expert "rt=" "rt_noforce=--contact-forces off" \
  "rgb_rt=--obs RGB" "rgb_rt_noforce=--obs RGB --contact-forces off"
in_time rgb && bench_variants rgb_tih ThreadInHole expert "rgb_tih=--obs RGB" "rgb_tih_all=--obs RGB $all 64"
if in_time pytest; then
  PYTHONPATH=$new timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py \
    -k "surface or forces or deferred" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
# 3. where the shading pass's ~1.3 ms per 4,096 64x64 frames goes: its variants timed with CUDA events on one env
#    step's replayed render launches (shade_probe.py), ThreadInHole and RopeThreading
for task in ThreadInHole RopeThreading; do
  PYTHONPATH=$new timeout 150 python3 $p/shade_probe.py $task "$n" "$out/shade_$task.json" > "$out/shade_$task.txt" 2>&1
  echo "shade_$task rc=$? $(grep -E '^(orig48|bg_only|no_store|flat) ' "$out/shade_$task.txt" | tr '\n' ' ')"
done
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1100}"
