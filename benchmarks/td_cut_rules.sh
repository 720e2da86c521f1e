#!/usr/bin/env bash
# TissueDissection's step under each cut rule, side by side in one call (issue #17: the 200k STATE / RGB targets were
# met by centroid; touch, sofa_env's rule, has been the default since the twenty-fifth session):
#   bash benchmarks/td_cut_rules.sh OUT_DIR
# Per rule (touch, centroid): bench_env.py --policy replay (the rule's own expert actions recorded, then replayed:
# env.step alone), STATE and 64x64 RGB, 4,096 envs; profile_step.py (kernel times without the CUDA graph, after
# 60 expert steps); bench_reset.py (a reset of every env after 40 expert steps, with cuts, against one after 40 idle
# steps). DEVICE (default cuda:0), NUM_ENVS (4096), SECONDS_PER_POINT (3) and PYTHON (python3) override.
set -u
out=${1:?usage: td_cut_rules.sh OUT_DIR}
mkdir -p "$out"
py=${PYTHON:-python3}
here=$(cd "$(dirname "$0")" && pwd)
for rule in touch centroid; do
  for obs in STATE RGB; do
    name=${rule}_${obs}
    "$py" "$here/bench_env.py" --task TissueDissection --device "${DEVICE:-cuda:0}" --num-envs "${NUM_ENVS:-4096}" \
      --seconds "${SECONDS_PER_POINT:-3}" --obs "$obs" --image-size 64 --policy replay --replay-steps 200 \
      --set "cut_removal=$rule" --out "$out/$name.json" > "$out/$name.txt" 2>&1
    echo "$name rc=$? $(tail -1 "$out/$name.txt")" | tee -a "$out/summary.txt"
  done
  "$py" "$here/profile_step.py" --task TissueDissection --device "${DEVICE:-cuda:0}" --num-envs "${NUM_ENVS:-4096}" \
    --warmup 60 --steps 20 --timing all --set "cut_removal=$rule" --out "$out/profile_$rule.json" \
    > "$out/profile_$rule.txt" 2>&1
  echo "profile_$rule rc=$?" | tee -a "$out/summary.txt"
  "$py" "$here/bench_reset.py" --tasks TissueDissection --device "${DEVICE:-cuda:0}" --num-envs "${NUM_ENVS:-4096}" \
    --set "cut_removal=$rule" --out "$out/reset_$rule.json" > "$out/reset_$rule.txt" 2>&1
  echo "reset_$rule rc=$? $(tail -1 "$out/reset_$rule.txt")" | tee -a "$out/summary.txt"
done
"$py" "$here/profile_step.py" --diff "$out/profile_touch.json" "$out/profile_centroid.json" --top 15 \
  > "$out/profile_diff.txt" 2>&1
echo "profile_diff (touch - centroid) rc=$?" | tee -a "$out/summary.txt"
