#!/usr/bin/env bash
# The forty-third session's quick call (one H200), same call, in order of need (LIMIT seconds, default 480):
# 1. RopeThreading (expert, 4,096 envs): HEAD (the grasped segments' orientation hold in the World's attachment pass,
#    the substep prediction in the fused rod launch) against --predict-in-rod-sweep off (the hold only) and the old
#    tree (.device/small/old = 8aeaf7e: neither), alternated twice; RopeCutting and PickAndPlace with the prediction on
#    and off; RopeThreading's rod launch at 64 lanes per env (32);
# 2. GPU tests of both (the prediction in the rod sweep against the separate launch, grasping, PickAndPlace's hold);
# 3. the experts (256 first episodes): RopeThreading, bimanual, RopeCutting, PickAndPlace.
# Lines go to stdout as they finish; files under $OUT/q43, packed into $OUT/q43.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-480}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q43
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q43.tgz" -C "$OUT" q43; }
. train/device/beside_lib.sh  # bench, bench_old
for r in a b; do
  bench "rt_$r" RopeThreading expert
  bench "rt_nopred_$r" RopeThreading expert --predict-in-rod-sweep off
  bench_old "rt_old_$r" RopeThreading expert
  pack
done
bench rc RopeCutting expert
bench rc_nopred RopeCutting expert --predict-in-rod-sweep off
bench pnp PickAndPlace expert
bench pnp_nopred PickAndPlace expert --predict-in-rod-sweep off
bench rt_lanes64 RopeThreading expert --rod-block-threads 64
pack
if [ "$(left)" -gt 80 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 -m pytest -q -p no:cacheprovider tests/test_physics_basic.py \
    tests/test_grasping.py tests/test_physics_rods.py -k "prediction or grasp or fused or hold" --device "$dev" \
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
expert expert_rt RopeThreading --config --config bimanual=true
expert expert_rc RopeCutting --config
expert expert_pnp PickAndPlace --config --config start_grasped=true randomize_torus_position=false
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
