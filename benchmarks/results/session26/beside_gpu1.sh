#!/usr/bin/env bash
# GPU 1 of the next lease (next_lease.md): TissueDissection's step, profile and resets under both cut rules; the
# resets of RopeCutting and PrecisionCutting with bench_reset.py's equal-steps method (twenty-sixth session); then
# GPU 1's learning queue until DEADLINE seconds after this script started. Run from the code copy (queue.sh's BESIDE).
# DEVICE (cuda:1), NUM_ENVS (4096) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:1}
n=${NUM_ENVS:-4096}
DEVICE=$dev NUM_ENVS=$n bash benchmarks/td_cut_rules.sh /tmp/r/td_rules
python3 benchmarks/bench_reset.py --tasks RopeCutting --device "$dev" --num-envs "$n" --set num_ropes_to_cut=3 \
  --out /tmp/r/td_rules/reset_rc.json 2>&1 | tail -1
python3 benchmarks/bench_reset.py --tasks PrecisionCutting --device "$dev" --num-envs "$n" --repeats 3 \
  --out /tmp/r/td_rules/reset_pc.json 2>&1 | tail -1
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
python3 train/experiments.py --queue benchmarks/results/session26/next_jobs_gpu1.txt --devices "$dev" --fast-pixels \
  --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs1
