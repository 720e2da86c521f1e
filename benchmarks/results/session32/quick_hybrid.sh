#!/usr/bin/env bash
# A short lease of the thirty-second session (~230 s on one GPU): the hybrid chain solve (kernels/chains_hybrid.py:
# the block solve's packs, P rows per lane eliminated in registers, PCR over one interface row per lane) against the
# serial solve in the same call: physics alone (the free 40 x 40 cloth, a 100-segment rod) at 1, 2 and 4 rows per lane,
# its GPU tests, then PrecisionCutting and RopeCutting with the expert, and PickAndPlace's expert on the packed block
# solve (its new GPU default). Results under $OUT/q32.
set -u
t0=$(date +%s)
limit=${LIMIT:-230}
dev=${DEVICE:-cuda:0}
out=$OUT/q32
mkdir -p "$out"
export PYTHONPATH=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME [bench_env.py options...]
  local name=$1
  shift
  [ "$(left)" -gt 25 ] || { echo "$name skipped (time)"; return; }
  timeout "$(left)" python3 benchmarks/bench_env.py --device "$dev" --num-envs 4096 --seconds 3 --policy expert \
    --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
timeout 80 python3 benchmarks/bench_physics.py --device "$dev" --num-envs 4096 --scene cloth_free rod \
  --chain-solver thomas hybrid --lane-rows 1 2 4 --steps 20 --settle-steps 5 --out "$out/phys.jsonl" \
  > "$out/phys.txt" 2>&1
echo "physics rc=$?"; grep "env-steps/s" "$out/phys.txt"
timeout 70 python3 -m pytest -q -x -p no:cacheprovider tests/test_chains_hybrid.py --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
b pc_thomas --task PrecisionCutting --set chain_solver=thomas
b pc_hybrid4 --task PrecisionCutting --set chain_solver=hybrid --lane-rows 4
b pc_hybrid2 --task PrecisionCutting --set chain_solver=hybrid --lane-rows 2
b rc_thomas --task RopeCutting --set chain_solver=thomas
b rc_hybrid4 --task RopeCutting --set chain_solver=hybrid --lane-rows 4
if [ "$(left)" -gt 30 ]; then
  timeout "$(left)" python3 benchmarks/expert_success.py --task PickAndPlace --device "$dev" --num-envs 256 \
    --action-types CONTINUOUS --out "$out/expert_pp.jsonl" > "$out/expert_pp.txt" 2>&1
  echo "expert_pp rc=$? $(tail -1 "$out/expert_pp.txt" | cut -c1-300)"
fi
echo "done in $(( $(date +%s) - t0 )) s"
