#!/usr/bin/env bash
# The forty-first session's second quick call (one H200), same call, in order of need (LIMIT seconds, default 370):
# 1. PrecisionCutting (expert, 4,096 envs): the triangle sweep with a box per tool ('shape_codes': 21 triangles past
#    the cull instead of 160, CPU count) and the three-walk chain solve ('open_walk': 67.6 % of the step is the cloth's
#    four-walk solve), each alone and together, against the defaults; TissueDissection with 'shape_codes';
# 2. GPU tests of both (tests/test_chains_open_walk.py, the triangle-sweep tests of tests/test_contact.py);
# 3. the chain walks at 128 registers (the four-walk's 96-register cap spills a 192 B frame, the three-walk's 64 B);
# 4. RopeThreading's profile after 20 warm-up steps (for the next session's CPU work), as far as the time goes.
# Lines go to stdout as they finish; files under $OUT/q41b, packed into $OUT/q41b.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-370}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q41b
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q41b.tgz" -C "$OUT" q41b; }
. train/device/beside_lib.sh  # bench (PYTHONPATH=$new)
bench pc PrecisionCutting expert
bench pc_sc PrecisionCutting expert --triangle-sweep shape_codes
pack
bench pc_open PrecisionCutting expert --set chain_solver=open_walk
bench pc_open_sc PrecisionCutting expert --set chain_solver=open_walk --triangle-sweep shape_codes
pack
bench td TissueDissection expert
bench td_sc TissueDissection expert --triangle-sweep shape_codes
pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_open_walk.py \
    tests/test_contact.py -k "open_walk or shape_code or triangle_sweep or outcode" --device "$dev" \
    > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
  pack
fi
[ "$(left)" -gt 45 ] && bench pc_open_cap128 PrecisionCutting expert --set chain_solver=open_walk \
  --max-registers solve_open_chains=128 && pack
[ "$(left)" -gt 45 ] && bench pc_cap128 PrecisionCutting expert --max-registers solve_chains=128 && pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/profile_step.py --task RopeThreading --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_RopeThreading.json" \
    > "$out/profile_RopeThreading.txt" 2>&1
  echo "profile_RopeThreading rc=$? $(head -3 "$out/profile_RopeThreading.txt" | tr '\n' ' ' | cut -c1-400)"
  pack
fi
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
