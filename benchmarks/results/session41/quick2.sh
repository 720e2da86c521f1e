#!/usr/bin/env bash
# The forty-first session's second quick call (one H200), same call, in order of need (LIMIT seconds, default 330):
# 1. PrecisionCutting (expert, 4,096 envs): its cloth's serial chain walk (solve_chains, 67.6 % of the step, capped at
#    96 registers since the twenty-fifth session, a 192 B spill frame on sm_90) against chain_solver 'open_walk'
#    (chains.solve_open_chains: three walks per Newton step instead of four, a 64 B frame at 96), then both at other
#    caps (the serial walk at 80 / 128: 248 / 80 B frames; the open walk at 80 and uncapped, 116 registers);
# 2. RopeThreading's profile after 20 warm-up steps on the current code (for the next session's CPU work);
# 3. LigatingLoop's step with its new default caps (the particle contact at 64), as far as the time goes.
# Lines go to stdout as they finish; files under $OUT/q41b, packed into $OUT/q41b.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-330}
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
bench pc_open PrecisionCutting expert --set chain_solver=open_walk
pack
for cap in 80 128; do
  [ "$(left)" -gt 45 ] || break
  bench "pc_cap$cap" PrecisionCutting expert --max-registers solve_chains="$cap"
  [ "$(left)" -gt 45 ] || break
  bench "pc_open_cap$cap" PrecisionCutting expert --set chain_solver=open_walk --max-registers solve_open_chains="$cap"
  pack
done
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/profile_step.py --task RopeThreading --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_RopeThreading.json" \
    > "$out/profile_RopeThreading.txt" 2>&1
  echo "profile_RopeThreading rc=$? $(head -3 "$out/profile_RopeThreading.txt" | tr '\n' ' ' | cut -c1-400)"
  pack
fi
[ "$(left)" -gt 45 ] && bench ll LigatingLoop expert && pack
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
