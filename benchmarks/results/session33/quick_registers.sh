#!/usr/bin/env bash
# A short single-GPU lease of the thirty-third session: the register-resident chain solve (kernels/chains_registers.py,
# chain_solver="registers": the serial walk unrolled to the chain length, the chain in registers for every Newton step)
# against the serial walk ("thomas") in the same call: RopeCutting with the expert (five 19-link ropes per env, 4 Newton
# steps at 40 substeps: the serial walk took 63 % of its step), the free 40 x 40 cloth in physics alone (39-link chains,
# the kernel spilling ~5 KB per thread), ThreadInHole (one 11-link thread per env), the GPU tests, PrecisionCutting.
# Everything under $OUT/q33, packed into $OUT/q33.tgz at the end (a call returns at most 8 files).
set -u
t0=$(date +%s)
limit=${LIMIT:-230}
dev=${DEVICE:-cuda:0}
out=$OUT/q33
mkdir -p "$out"
export PYTHONPATH=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME [bench_env.py options...]
  local name=$1
  shift
  [ "$(left)" -gt 30 ] || { echo "$name skipped (time)"; return; }
  timeout $(( $(left) - 10 )) python3 benchmarks/bench_env.py --device "$dev" --num-envs 4096 --seconds 3 \
    --policy expert --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
b rc_thomas --task RopeCutting --set chain_solver=thomas
b rc_registers --task RopeCutting --set chain_solver=registers
if [ "$(left)" -gt 40 ]; then
  timeout $(( $(left) - 10 )) python3 benchmarks/bench_physics.py --device "$dev" --num-envs 4096 --scene cloth_free \
    --chain-solver thomas registers --steps 20 --settle-steps 5 --out "$out/phys.jsonl" > "$out/phys.txt" 2>&1
  echo "physics rc=$?"; grep "env-steps/s" "$out/phys.txt"
fi
b tih_thomas --task ThreadInHole --set chain_solver=thomas
b tih_registers --task ThreadInHole --set chain_solver=registers
if [ "$(left)" -gt 40 ]; then
  timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py --device "$dev" \
    > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
b pc_thomas --task PrecisionCutting --set chain_solver=thomas
b pc_registers --task PrecisionCutting --set chain_solver=registers
echo "done in $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q33.tgz" -C "$OUT" q33 && rm -rf "$out"
