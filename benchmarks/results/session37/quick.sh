#!/usr/bin/env bash
# A short single-GPU lease of the thirty-seventh session (the x2 lease left ~400 s), same call throughout:
# LigatingLoop's step alone (the expert's recorded actions replayed: #18's "whole env.step") against the expert timed
# with it; ThreadInHole with its hole's rotations refreshed once per physics step (hole_rotation_refresh=4: the
# refresh kernel was 10.2 % of its kernel time at every sweep) against the default, then replayed; RopeThreading
# replayed. Lines go to stdout as they finish (a call cut short by the lease still returns them); files under $OUT/q37,
# packed into $OUT/q37.tgz at the end.
set -u
t0=$(date +%s)
limit=${LIMIT:-200}
dev=${DEVICE:-cuda:0}
out=$OUT/q37
mkdir -p "$out"
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME TASK POLICY [bench_env.py options...]
  local name=$1 task=$2 policy=$3
  shift 3
  [ "$(left)" -gt 25 ] || { echo "$name skipped (time)"; return; }
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/bench_env.py --task "$task" --device "$dev" \
    --num-envs 4096 --seconds 3 --policy "$policy" --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt") at $(( $(date +%s) - t0 )) s"
  tar czf "$OUT/q37.tgz" -C "$OUT" q37
}
b ll_replay LigatingLoop replay --replay-steps 150
b ll_expert LigatingLoop expert
b tih_expert ThreadInHole expert
b tih_refresh4 ThreadInHole expert --set hole_rotation_refresh=4
b tih_replay_refresh4 ThreadInHole replay --replay-steps 150 --set hole_rotation_refresh=4
b rt_replay RopeThreading replay --replay-steps 150
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
