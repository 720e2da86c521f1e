#!/usr/bin/env bash
# The thirty-ninth session's quick call (one H200), same call, in order of need (LIMIT seconds, default 470):
# 1. GPU tests of the session's changes (the surface BVH refit once per env step, the per-vertex solve's start in
#    the prediction);
# 2. ThreadInHole on the new code (one refit per env step, no begin_substep launch) against the same code refitting
#    at every physics step (--surface-refit-steps 1) and the lease's code (68ffe12, carried as .device/small/old);
# 3. LigatingLoop the same way (its refit per env step: 2 -> 1), with nvidia-smi sampling the clocks and power
#    throughout: its bench step is 43.0 ms where the lease's graph profile saw 36.96 ms of device span per step at
#    steps 10-15, so 4. the step by phase (the expert's actions replayed: steps 5-20 against 5-150) and a profile at
#    steps 60-65 against the lease's 10-15 answer whether later states cost more or the clocks drop;
# 5. RopeThreading's hybrid chain kernel without its loop and cut branches against the lease's code;
# 6. ThreadInHole's continuous expert on the new code, as far as the time goes.
# Lines go to stdout as they finish; files under $OUT/q39, packed into $OUT/q39.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-470}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q39
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
[ -d "$PWD/.device/small/old/lapwarp" ] || echo "no old tree at $PWD/.device/small/old: the old runs will fail"
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q39.tgz" -C "$OUT" q39; }
. train/device/beside_lib.sh  # bench (PYTHONPATH=$new)
bench_old() {  # NAME TASK POLICY [options]: bench on the old tree
  local name=$1 task=$2 policy=$3
  shift 3
  PYTHONPATH=$old python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy "$policy" "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
nvidia-smi --query-gpu=timestamp,clocks.sm,clocks.max.sm,power.draw,power.limit,temperature.gpu,clocks_throttle_reasons.active \
  --format=csv -lms 250 > "$out/smi.csv" 2>&1 &
smi=$!
PYTHONPATH=$new timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py tests/test_fused_tets.py \
  -k "stale_surface or surface_refit or start_in_the_prediction or matches_the_per_colour" --device "$dev" \
  > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
pack
bench tih ThreadInHole expert
bench tih_refit1 ThreadInHole expert --surface-refit-steps 1
bench_old tih_old ThreadInHole expert
pack
echo "ll start $(date +%s.%N)" >> "$out/marks.txt"
bench ll LigatingLoop expert
echo "ll end $(date +%s.%N)" >> "$out/marks.txt"
bench ll_refit1 LigatingLoop expert --surface-refit-steps 1
bench ll_replay20 LigatingLoop replay --replay-steps 20
bench ll_replay150 LigatingLoop replay --replay-steps 150
pack
# RopeThreading's hybrid chain solve compiled without the loop and cut branches (its rope is open and uncut: 217
# registers per lane without a spill against 255 with a 112-byte spill frame, sm_90) against the lease's code
bench rt RopeThreading expert
bench_old rt_old RopeThreading expert
pack
if [ "$(left)" -gt 70 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/profile_step.py --task LigatingLoop --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 60 --top 30 --out "$out/profile_ll_w60.json" > "$out/profile_ll_w60.txt" 2>&1
  echo "profile_ll_w60 rc=$? $(head -1 "$out/profile_ll_w60.txt" | cut -c1-200) at $(( $(date +%s) - t0 )) s"
  pack
fi
if [ "$(left)" -gt 60 ]; then
  bench_old ll_old LigatingLoop expert
  pack
fi
if [ "$(left)" -gt 50 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --config configuration=normal --config configuration=flexible \
    --config configuration=inverted --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
  echo "expert_tih rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
fi
kill "$smi" 2>/dev/null
pack
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
