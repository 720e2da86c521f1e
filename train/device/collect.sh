#!/usr/bin/env bash
# Wait up to SECONDS (or until the queue of train/device/queue.sh is done), then pack what has finished into
# $OUT/r.tgz (checkpoints left out: one returned file is limited to 16 MiB). Call it back to back: a lease is given
# back after ~30 s idle.
#
#   bash train/device/collect.sh SECONDS
set -uo pipefail
end=$(( $(date +%s) + $1 ))
while [ "$(date +%s)" -lt "$end" ] && ! grep -q ALLDONE /tmp/r/done.txt 2>/dev/null; do sleep 10; done
grep -E "started|finished|FAILED" /tmp/r/queue.log | tail -40
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv
cd /tmp && tar czf "$OUT/r.tgz" --exclude='*.pt' r && ls -la "$OUT"
