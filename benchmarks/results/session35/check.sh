#!/usr/bin/env bash
# The thirty-fifth session's last short call: the register solve's env test with the GPU's 0.2 mm pluck (the 2 mm one
# folds links, a bifurcation rounding decides), the fused tets and ThreadInHole's tests on the GPU, and ThreadInHole's
# step with its new default cap (the lagged per-vertex sweep at 64 registers; measured 143.1k as a bench option).
set -u
dev=${DEVICE:-cuda:0}
out=$OUT/c35
mkdir -p "$out"
PYTHONPATH=/tmp/site:$PWD timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py \
  -k env_config --device "$dev" > "$out/pytest_registers_cuda.txt" 2>&1
echo "pytest registers rc=$? $(tail -1 "$out/pytest_registers_cuda.txt")"
PYTHONPATH=/tmp/site:$PWD timeout 60 python3 benchmarks/bench_env.py --task ThreadInHole --device "$dev" --num-envs 4096 \
  --seconds 3 --policy expert --out "$out/tih_default.json" > "$out/tih_default.txt" 2>&1
echo "tih_default rc=$? $(tail -1 "$out/tih_default.txt")"
tar czf "$OUT/c35.tgz" -C "$OUT" c35 && rm -rf "$out"
