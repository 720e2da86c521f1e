#!/usr/bin/env bash
# Start a detached learning queue on a GPU machine (the `device` tool's lease) and return in ~30 s.
#
#   bash train/device/queue.sh JOBS_FILE NUM_GPUS [COMMIT [DEADLINE]]
#
# Run from the checkout's copy on the machine. JOBS_FILE holds `EXPERIMENT ROW SEED [SEED ...]` lines
# (train/experiments.py --queue). The checkout is copied to /tmp/queue_code first, so a later call's copy of the
# working tree cannot change the code under the running jobs. COMMIT (the copy leaves out .git, whose HEAD is stale
# there: pass `$(git rev-parse --short HEAD)` from here, committed tree) is recorded in every result. Python packages are read
# from /tmp/site (wheels installed with `pip install --no-index --no-deps --target /tmp/site`, see
# ../shared/tools/device-wheels.sh). DEADLINE (seconds; the lease's time left minus the last collection): runs not
# expected to end by then are skipped (experiments.py --deadline, estimated from the rows' committed results).
# Results: /tmp/r/learning/<experiment>/<row>/, log /tmp/r/queue.log, ALLDONE in /tmp/r/done.txt at the end;
# collect them with train/device/collect.sh. BESIDE (environment variable, optional): a command run detached beside
# the queue from the same copy of the code, its output in /tmp/r/beside.log and its files where it writes them under
# /tmp/r (e.g. a soak on the GPU the queue leaves free: NUM_GPUS 3 and
# BESIDE="python3 benchmarks/soak.py --device cuda:3 ... --out /tmp/r/soak.jsonl").
set -euo pipefail
jobs_file=$1
num_gpus=$2
code=$(cd "$(dirname "$0")/../.." && pwd)
rm -rf /tmp/queue_code && mkdir -p /tmp/queue_code
# no .git: the machine's copy of it names a stale HEAD (the session's first commit, seen as b101f32 for code at
# f67e92a in the twenty-sixth session), so the runs record COMMIT instead (experiments.git_commit's fallback)
(cd "$code" && tar --exclude=./.git --exclude=./.device --exclude=./runs --exclude=__pycache__ -cf - .) \
  | tar xf - -C /tmp/queue_code
# the trees a BESIDE script compares against (.device/small/old, probes beside it; .device is left out above:
# wheels): its commands run from this copy
if [ -d "$code/.device/small" ]; then
  mkdir -p /tmp/queue_code/.device/small
  # a .device/small holding only files (wheels) has no tree: the unmatched glob stays literal, so skip it
  for tree in "$code"/.device/small/*/; do [ -d "$tree" ] || continue; cp -r "$tree" /tmp/queue_code/.device/small/; done
fi
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site:/tmp/queue_code
export LAPWARP_COMMIT=${3:-}
deadline=${4:+--deadline $4}
mkdir -p /tmp/r && cp "$jobs_file" /tmp/r/jobs.txt
nvidia-smi --query-gpu=name,driver_version --format=csv > /tmp/r/gpu.txt
devices=$(for g in $(seq 0 $((num_gpus - 1))); do echo -n "cuda:$g "; done)
cd /tmp/queue_code
setsid nohup bash -c "python3 train/experiments.py --queue /tmp/r/jobs.txt --devices $devices --fast-pixels \
  --shared-encoder --skip-done --no-plots $deadline --out /tmp/r/learning --log-dir /tmp/queue_runs > /tmp/r/queue.log 2>&1; \
  echo ALLDONE >> /tmp/r/done.txt" > /dev/null 2>&1 &
if [ -n "${BESIDE:-}" ]; then
  setsid nohup bash -c "$BESIDE > /tmp/r/beside.log 2>&1; echo \"BESIDE exit \$?\" >> /tmp/r/beside.log" \
    > /dev/null 2>&1 &
fi
sleep 30
cat /tmp/r/queue.log
[ -z "${BESIDE:-}" ] || tail -5 /tmp/r/beside.log
