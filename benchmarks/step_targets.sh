#!/usr/bin/env bash
# The #17 / #18 step-throughput targets, the step alone and with the expert timed, side by side in one call:
#   bash benchmarks/step_targets.sh OUT_DIR [TASK ...]   (default: the Dissection and Thread Manipulation tasks)
# For each task, STATE and 64x64 RGB, 4,096 envs: bench_env.py --policy replay (the expert's recorded actions
# replayed into a fresh env of the same seed: env.step alone, in the expert's regime) and --policy expert (the scripted
# expert's own work timed too, the figure of earlier sessions). JSON per run in OUT_DIR; summary.txt lists them.
# REPLAY_STEPS (default 200) expert steps are recorded first: PrecisionCutting's take ~45 s on an H100, so split the
# tasks over calls of a 10-minute limit. DEVICE, NUM_ENVS and SECONDS_PER_POINT override cuda:0, 4096 and 3; SET
# (space-separated KEY=VALUE config overrides, e.g. SET="cut_removal=centroid") is passed to every run's --set.
set -u
out=${1:?usage: step_targets.sh OUT_DIR [TASK ...]}; shift
tasks=${*:-RopeCutting PrecisionCutting TissueDissection ThreadInHole RopeThreading LigatingLoop}
mkdir -p "$out"
py=${PYTHON:-python3}
here=$(cd "$(dirname "$0")" && pwd)
for task in $tasks; do
  for obs in STATE RGB; do
    for policy in replay expert; do
      name=${task}_${obs}_${policy}
      "$py" "$here/bench_env.py" --task "$task" --device "${DEVICE:-cuda:0}" --num-envs "${NUM_ENVS:-4096}" \
        --seconds "${SECONDS_PER_POINT:-3}" --obs "$obs" --image-size 64 --policy "$policy" \
        --replay-steps "${REPLAY_STEPS:-200}" ${SET:+--set $SET} --out "$out/$name.json" > "$out/$name.txt" 2>&1
      echo "$name rc=$? $(tail -1 "$out/$name.txt")" | tee -a "$out/summary.txt"
    done
  done
done
