#!/usr/bin/env bash
# A short lease of the thirty-first session (~220 s on one GPU): the block chain solve with packs (chains.pack_chains:
# a family's open chains end to end in blocks of up to 128 rows) against a chain per block (--pcr-rows 1) and the
# serial solve, where the one-chain-per-block solve lost: RopeCutting (5 ropes of 19 links per env), the free cloth
# (rows, columns and 79 diagonals of 1-39 links), PrecisionCutting. Results under $OUT/q31.
set -u
t0=$(date +%s)
limit=${LIMIT:-220}
dev=${DEVICE:-cuda:0}
out=$OUT/q31
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
b rc_thomas --task RopeCutting --set chain_solver=thomas
b rc_pcr_pack128 --task RopeCutting --set chain_solver=pcr
b rc_pcr_chain --task RopeCutting --set chain_solver=pcr --pcr-rows 1
timeout "$(left)" python3 benchmarks/bench_physics.py --device "$dev" --num-envs 4096 --scene cloth_free \
  --chain-solver thomas pcr --pcr-rows 0 1 --steps 20 --settle-steps 5 --out "$out/phys.jsonl" > "$out/phys.txt" 2>&1
echo "physics rc=$?"; cat "$out/phys.txt"
b pc_pcr_pack128 --task PrecisionCutting --set chain_solver=pcr
b rc_pcr_pack64 --task RopeCutting --set chain_solver=pcr --pcr-rows 64
echo "done in $(( $(date +%s) - t0 )) s"
