#!/usr/bin/env bash
# The forty-seventh session's quick call (one H200, after the lease), each item skipped once DEADLINE (s, default 330)
# has passed; lines to stdout as they finish, files under $OUT/q47 packed into $OUT/q47.tgz:
# 1. ThreadInHole (expert) with its hole held at rest (World.tet_hold_speed, the new default) against
#    hole_hold_speed=0, STATE and RGB 64x64 (with the shading pass's clear last), and random actions;
# 2. RopeThreading RGB (the shading pass's clear last; the lease: 185.2k) and LigatingLoop (deferred surface deltas and
#    fused surface boxes at 64 lanes, its defaults now; the lease: 101.8k before, 102.9k deferred alone);
# 3. the shading probe's second round (clear last / first / none + a fill launch);
# 4. GPU tests of the hold (a pressed block against the unheld solve; ThreadInHole's thread on the wall);
# 5. ThreadInHole's 10^7-step random-action soak with the hold.
set -u
. train/device/beside_lib.sh
DEADLINE=${DEADLINE:-330} beside_init "$OUT/q47"
export PYTHONUNBUFFERED=1
pack() { tar czf "$OUT/q47.tgz" -C "$OUT" q47; }
in_time tih && bench_variants tih ThreadInHole expert "tih=" "tih_nohold=--set hole_hold_speed=0" \
  "rgb_tih=--obs RGB" "rgb_tih_nohold=--obs RGB --set hole_hold_speed=0"
pack
in_time tih_random && bench_variants tih_random ThreadInHole random "tih_random=" \
  "tih_random_nohold=--set hole_hold_speed=0"
pack
in_time rt && bench_variants rt RopeThreading expert "rgb_rt=--obs RGB"
in_time ll && bench_variants ll LigatingLoop expert "ll="
pack
in_time probe && {
  PYTHONPATH=$new timeout 100 python3 benchmarks/results/session47/probes/shade_probe2.py ThreadInHole "$n" \
    "$out/shade2_ThreadInHole.json" > "$out/shade2_ThreadInHole.txt" 2>&1
  echo "shade2 rc=$? $(grep -E '^(clear_last|clear_first|no_clear|no_clear_fill) ' "$out/shade2_ThreadInHole.txt" | tr '\n' ' ')"
  pack
}
if in_time pytest; then
  PYTHONPATH=$new timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_tet_hold.py tests/test_render.py \
    --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
  pack
fi
in_time soak && soak ThreadInHole 10000000
pack
echo "done in $(( $(date +%s) - t0 )) s"
