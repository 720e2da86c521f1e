#!/usr/bin/env bash
# GPU 1 of the next lease (next_lease.md; GPU 3 on an x4 machine: DEVICE=cuda:3 JOBS=.../next_jobs_gpu3.txt):
# RopeCutting's reset profiled kernel by kernel, cut against uncut (its cut reset cost 1.13x the uncut one on an H200 in
# the twenty-seventh session, 0.91x on the CPU; bench_reset.py --profile); PrecisionCutting's step with the scissors
# expert by lapwarp's centroid rule and by sofa_env's vertex rule (cut_removal, new); kernel profiles of RopeCutting's
# step and of TissueDissection's RGB against its STATE step (~3 min in all); then a learning queue until
# DEADLINE seconds after this script started. Run from the code copy (queue.sh's BESIDE).
# DEVICE (cuda:1), NUM_ENVS (4096), JOBS (next_jobs_gpu1.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:1}
n=${NUM_ENVS:-4096}
out=/tmp/r/beside27
mkdir -p "$out"
python3 benchmarks/bench_reset.py --tasks RopeCutting --device "$dev" --num-envs "$n" --set num_ropes_to_cut=3 \
  --profile "$out/reset_profile" --out "$out/reset_rc.json" > "$out/reset_rc.txt" 2>&1
echo "reset_rc rc=$?"; cat "$out/reset_rc.txt" | grep -v Warning | tail -20
for rule in centroid vertex; do
  python3 benchmarks/bench_env.py --task PrecisionCutting --device "$dev" --num-envs "$n" --seconds 3 --obs STATE \
    --policy expert --set "cut_removal=$rule" --out "$out/pc_$rule.json" > "$out/pc_$rule.txt" 2>&1
  echo "pc_$rule rc=$? $(tail -1 "$out/pc_$rule.txt")"
done
# PrecisionCutting's scripted expert in every configuration by both cut rules, 256 envs (the continuous expert gives
# up a target it stands at for 15 steps since the twenty-seventh session, as the discrete one did)
for rule in centroid vertex; do
  python3 benchmarks/expert_success.py --task PrecisionCutting --device "$dev" --num-envs 256 --episodes 256 \
    --max-steps 520 --config cut_removal=$rule path_function=line --config cut_removal=$rule path_function=line \
    randomize_path=true --config cut_removal=$rule path_function=sine --config cut_removal=$rule path_function=sine \
    randomize_path=true --out "$out/pc_expert_$rule.jsonl" > "$out/pc_expert_$rule.txt" 2>&1
  echo "pc_expert_$rule rc=$?"; grep -o '"overrides".*"success_rate": [0-9.]*' "$out/pc_expert_$rule.jsonl" || true
done
# where the step's time goes now (the profiles on record are many sessions old): RopeCutting STATE, and TissueDissection
# 64x64 RGB against STATE (the renderer's share of the 2.8 ms between its RGB and STATE steps; RGB target 200k)
python3 benchmarks/profile_step.py --task RopeCutting --device "$dev" --num-envs "$n" --warmup 20 --steps 10 \
  --out "$out/profile_rc.json" > "$out/profile_rc.txt" 2>&1; echo "profile_rc rc=$?"; head -12 "$out/profile_rc.txt"
for obs in STATE RGB; do
  python3 benchmarks/profile_step.py --task TissueDissection --device "$dev" --num-envs "$n" --warmup 60 --steps 20 \
    --set observation_type=$obs image_shape=[64,64] --out "$out/profile_td_$obs.json" > "$out/profile_td_$obs.txt" 2>&1
  echo "profile_td_$obs rc=$?"
done
python3 benchmarks/profile_step.py --diff "$out/profile_td_RGB.json" "$out/profile_td_STATE.json" --top 20
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
python3 train/experiments.py --queue "${JOBS:-benchmarks/results/session27/next_jobs_gpu1.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
