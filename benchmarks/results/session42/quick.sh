#!/usr/bin/env bash
# The forty-second session's quick call (one H200), same call, in order of need (LIMIT seconds, default 420):
# 1. the rope Newton tolerance (World.rod_newton_tolerance: a chain stops its Newton steps once one corrected no link
#    by that much): RopeCutting's register solve at its new default 1e-7 m against every step (0), twice each
#    alternated; RopeThreading's hybrid solve at 0, 3e-5 (its new default) and 1e-4 m (expert, 4,096 envs);
# 2. GPU tests of the tolerance (register and hybrid kernels, RopeCutting's settle test on the register solve);
# 3. the experts on it (256 first episodes): RopeCutting's default, RopeThreading at 3e-5 and 1e-4 m.
# Lines go to stdout as they finish; files under $OUT/q42, packed into $OUT/q42.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-420}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q42
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q42.tgz" -C "$OUT" q42; }
. train/device/beside_lib.sh  # bench (PYTHONPATH=$new)
bench rc_tol0 RopeCutting expert --set rope_newton_tolerance=0
bench rc RopeCutting expert
bench rc_tol0_b RopeCutting expert --set rope_newton_tolerance=0
bench rc_b RopeCutting expert
pack
bench rt_tol0 RopeThreading expert --set rope_newton_tolerance=0
bench rt RopeThreading expert
bench rt_1e4 RopeThreading expert --set rope_newton_tolerance=1e-4
pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py \
    tests/test_chains_hybrid.py tests/test_rope_cutting.py -k "tolerance or settles" --device "$dev" \
    > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
  pack
fi
expert() {  # NAME TASK --config ...
  local name=$1 task=$2
  shift 2
  [ "$(left)" -gt 50 ] || { echo "skipped $name"; return 0; }
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task "$task" --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS "$@" --out "$out/$name.jsonl" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/$name.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
  pack
}
expert expert_rc RopeCutting --config num_ropes=5 --config num_ropes=10 num_ropes_to_cut=3
expert expert_rt RopeThreading --config
expert expert_rt_1e4 RopeThreading --config rope_newton_tolerance=1e-4
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
