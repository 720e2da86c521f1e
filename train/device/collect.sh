#!/usr/bin/env bash
# Wait up to SECONDS (or until the queue of train/device/queue.sh and its BESIDE command are done), then pack what
# has finished into $OUT/r.tgz (checkpoints left out: one returned file is limited to 16 MiB). Call it back to back:
# a lease is given back after ~30 s idle. Issue the queue call and every collect call of a lease together (one batch
# of calls, which run one after another with no gap): in the twenty-fourth session a collect call sent a moment after
# the previous one had returned found a fresh machine, and the queue's runs in flight were lost (it then waited its
# full time for nothing: now it stops at once when no queue is running here).
#
#   bash train/device/collect.sh SECONDS
set -uo pipefail
if [ ! -f /tmp/r/queue.log ]; then
  # a fresh machine (the lease went idle and was given back): waiting would only spend device time
  echo "no queue on this machine: the lease was given back and its runs are lost; install and run queue.sh again"
  exit 3
fi
all_done() {
  # the queue and, where queue.sh started one, the command beside it (e.g. a second GPU's queue) have ended
  grep -q ALLDONE /tmp/r/done.txt 2>/dev/null \
    && { [ ! -f /tmp/r/beside.log ] || grep -q "BESIDE exit" /tmp/r/beside.log; }
}
pack() {
  # written aside and renamed, so a call cut short (its limit lowered to the lease's device time left) still
  # returns the last whole archive
  (cd /tmp && tar czf "$OUT/r.part" --exclude='*.pt' r && mv "$OUT/r.part" "$OUT/r.tgz")
}
end=$(( $(date +%s) + $1 ))
n=0
while [ "$(date +%s)" -lt "$end" ] && ! all_done; do
  sleep 10
  n=$((n + 1))
  [ $((n % 6)) -ne 0 ] || pack
done
grep -E "started|finished|FAILED" /tmp/r/queue.log | tail -40
if [ -f /tmp/r/beside.log ]; then
  grep -E "started|finished|FAILED" /tmp/r/beside.log | tail -20
  tail -3 /tmp/r/beside.log
fi
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv
pack && ls -la "$OUT"
