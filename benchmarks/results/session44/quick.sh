#!/usr/bin/env bash
# The forty-fourth session's quick call (one H200), same call, in order of need (LIMIT seconds, default 380):
# 1. RopeCutting (expert, 4,096 envs): the old tree (.device/small/old = fbd00cc: the register solve unrolled to the
#    longest chain) against HEAD (its exact-length variant for the five equal 19-link ropes: spill frame 1,760 ->
#    672 B; and the prediction in the rod launch at 64 registers, +0.4 % in the lease) and the split solve (two threads per rope, --register-split on) uncapped (235 registers, 1.2 waves of
#    1,280 warps) and capped at 200 / 168 registers (one wave), alternated;
# 2. GPU tests of both (tests/test_chains_split.py, the equal-chain and RopeCutting register tests) and of the two
#    GPU comparisons whose tolerance the lease found too tight (the fused rod sweep, the hybrid attachment pass);
# 3. RopeCutting's expert (256 first episodes) on the split solve (--world chain_register_split=true);
# 4. RopeCutting on the hybrid solve (all five ropes in one pack per env: 100 rows at 4 per lane, 25 of a warp's
#    lanes, at 128 registers).
# Lines go to stdout as they finish; files under $OUT/q44, packed into $OUT/q44.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-380}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q44
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q44.tgz" -C "$OUT" q44; }
. train/device/beside_lib.sh  # bench, bench_old
timed() { [ "$(left)" -gt 30 ] || { echo "skipped $1"; return 1; }; }
timed rc_new_a && bench rc_new_a RopeCutting expert
timed rc_split_a && bench rc_split_a RopeCutting expert --register-split on
timed rc_split200_a && bench rc_split200_a RopeCutting expert --register-split on --max-registers solve_chains_split=200
timed rc_old_a && bench_old rc_old_a RopeCutting expert
pack
timed rc_split168_b && bench rc_split168_b RopeCutting expert --register-split on --max-registers solve_chains_split=168
timed rc_new_b && bench rc_new_b RopeCutting expert
timed rc_split200_b && bench rc_split200_b RopeCutting expert --register-split on --max-registers solve_chains_split=200
timed rc_old_b && bench_old rc_old_b RopeCutting expert
timed rc_split_b && bench rc_split_b RopeCutting expert --register-split on
pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 40 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_split.py \
    tests/test_chains_registers.py tests/test_physics_rods.py tests/test_chains_hybrid.py \
    -k "split or equal or env_config or fused_rod_sweep or closing_attachment" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
  pack
fi
if [ "$(left)" -gt 45 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task RopeCutting --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --world chain_register_split=true --out "$out/expert_rc_split.jsonl" \
    > "$out/expert_rc_split.txt" 2>&1
  echo "expert_rc_split rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_rc_split.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
  pack
fi
timed rc_hybrid4 && bench rc_hybrid4 RopeCutting expert --set chain_solver='"hybrid"' --lane-rows 4 \
  --max-registers solve_chains_hybrid=128
pack
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
