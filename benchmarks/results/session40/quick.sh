#!/usr/bin/env bash
# The fortieth session's quick call (one H200 or the first GPU of a lease), same call, in order of need (LIMIT
# seconds, default 330):
# 1. GPU tests of the clustered surface query (the thrown block against one leaf holding every triangle);
# 2. LigatingLoop, ThreadInHole and GraspLiftAndTouch on the new code (each env's surface boxes recomputed every
#    sweep, no wp.Mesh BVH, no drift) against 668d57e (carried as .device/small/old: the grouped BVH refit per
#    physics step / per env step);
# 3. LigatingLoop's and ThreadInHole's experts on the new code (a surface vertex counts in its contact average only
#    where the contact's weight on it is above 0), as far as the time goes.
# Lines go to stdout as they finish; files under $OUT/q40, packed into $OUT/q40.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-330}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q40
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
[ -d "$PWD/.device/small/old/lapwarp" ] || echo "no old tree at $PWD/.device/small/old: the old runs will fail"
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q40.tgz" -C "$OUT" q40; }
. train/device/beside_lib.sh  # bench (PYTHONPATH=$new)
bench_old() {  # NAME TASK POLICY [options]: bench on the old tree
  local name=$1 task=$2 policy=$3
  shift 3
  PYTHONPATH=$old python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy "$policy" "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
PYTHONPATH=$new timeout 90 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py \
  -k "clustered or surface" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
pack
bench ll LigatingLoop expert
bench_old ll_old LigatingLoop expert
pack
bench tih ThreadInHole expert
bench_old tih_old ThreadInHole expert
pack
bench glt GraspLiftAndTouch expert
bench_old glt_old GraspLiftAndTouch expert
pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task LigatingLoop --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --config loop_stiffness=stiff --config loop_stiffness=soft \
    --out "$out/expert_ll.jsonl" > "$out/expert_ll.txt" 2>&1
  echo "expert_ll rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_ll.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
  pack
fi
if [ "$(left)" -gt 50 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --config configuration=normal --config configuration=flexible \
    --config configuration=inverted --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
  echo "expert_tih rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
fi
pack
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
