#!/usr/bin/env bash
# The thirty-eighth session's last device minutes (one H200 after the x4 lease), same call: ThreadInHole's scripted
# expert on the PCR chain solve (its thread's chain; 164.4k against 160.2k for the serial walk in the lease, same call:
# the rule is to take a faster solve only after its expert ran on it), continuous, three configurations, 256 first
# episodes; then a random-action soak of LigatingLoop on its new default (cavity_rotation_iterations 1), as far as the
# time goes. Lines go to stdout as they finish; files under $OUT/q38, packed into $OUT/q38.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-230}
dev=${DEVICE:-cuda:0}
out=$OUT/q38
mkdir -p "$out"
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
left() { echo $(( limit - ($(date +%s) - t0) )); }
timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS --config configuration=normal chain_solver=pcr \
  --config configuration=flexible chain_solver=pcr --config configuration=inverted chain_solver=pcr \
  --out "$out/expert_tih_pcr.jsonl" > "$out/expert_tih_pcr.txt" 2>&1
echo "expert_tih_pcr rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih_pcr.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q38.tgz" -C "$OUT" q38
if [ "$(left)" -gt 60 ]; then
  timeout $(( $(left) - 5 )) python3 benchmarks/soak.py --device "$dev" --num-envs 4096 --env-steps 5e6 \
    --tasks LigatingLoop --action-types CONTINUOUS --out "$out/soak_ll.jsonl" > "$out/soak_ll.txt" 2>&1
  echo "soak_ll rc=$? $(tail -1 "$out/soak_ll.txt" | cut -c1-400) at $(( $(date +%s) - t0 )) s"
  tar czf "$OUT/q38.tgz" -C "$OUT" q38
fi
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
