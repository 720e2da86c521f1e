#!/usr/bin/env bash
# The forty-first session's quick call (one H200), same call, in order of need (LIMIT seconds, default 300):
# 1. GPU tests of the shared-memory chain solve (kernels/chains_shared.py against the serial walk);
# 2. PrecisionCutting (expert, 4,096 envs): the serial walk with the cloth's edges numbered in slot order (new)
#    against ca50769 (carried as .device/small/old: edges numbered by colour), then chain_solver 'shared' at 64 and
#    40 lanes (a block per env; a similar kernel lost in the thirty-eighth session: 17.9k / 20.4k against 24.8k).
# Lines go to stdout as they finish; files under $OUT/q41, packed into $OUT/q41.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q41
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
[ -d "$PWD/.device/small/old/lapwarp" ] || echo "no old tree at $PWD/.device/small/old: the old runs will fail"
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q41.tgz" -C "$OUT" q41; }
. train/device/beside_lib.sh  # bench (PYTHONPATH=$new), bench_old (PYTHONPATH=$old)
PYTHONPATH=$new timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_chains_shared.py --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
pack
bench pc PrecisionCutting expert
bench_old pc_old PrecisionCutting expert
pack
for lanes in 64 40; do
  [ "$(left)" -gt 40 ] || break
  bench "pc_shared$lanes" PrecisionCutting expert --set chain_solver=shared --shared-lanes "$lanes"
  pack
done
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
