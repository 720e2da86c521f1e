#!/usr/bin/env bash
# Multi-GPU training scaling (issue #20): the same task and per-rank settings on 1 and 2 GPUs of one machine.
#   bash benchmarks/multi_gpu_scaling.sh OUT_DIR [state|rgb|same|deformable|cold ...]   (default: cold state rgb)
# cold:  start-up with empty Warp kernel caches, 1 rank vs 2 ranks compiling at once (1 PPO iteration each)
# state: Reach from state, 4,096 envs per rank; 150 iterations on 1 GPU vs 75 per rank on 2 (same total env-steps)
#        and 150 per rank on 2 (same iterations)
# rgb:   Reach from 64x64 RGB, 4,096 envs per rank, 150 vs 2 x 75 iterations
# same:  the 2-GPU Reach runs again with --same-global-minibatch (the global mini-batch and optimiser steps per
#        env-step of the 1-GPU run): state and RGB, 2 x 75 iterations
# deformable: TissueManipulation from state (a task whose env step, not the PPO update, dominates an iteration),
#        4,096 envs per rank, 150 vs 2 x 75 iterations
# Each run's console output, progress CSV and result JSON go to OUT_DIR; walls.txt lists exit status and wall time.
set -u
out=${1:?usage: multi_gpu_scaling.sh OUT_DIR [cold state rgb]}; shift
parts=${*:-cold state rgb}
mkdir -p "$out"
py=${PYTHON:-python3}
torchrun=("$py" -m torch.distributed.run --standalone --nproc_per_node=2)
cache=$(mktemp -d)

run() {  # name, command...
  local name=$1; shift
  local start end status
  start=$(date +%s.%N)
  "$@" --progress-csv "$out/$name.csv" --result-json "$out/$name.json" > "$out/$name.txt" 2>&1
  status=$?
  end=$(date +%s.%N)
  echo "$name rc=$status wall=$("$py" -c "print(round($end - $start, 1))")" | tee -a "$out/walls.txt"
  grep -E "^training|^trained|^evaluation|Error" "$out/$name.txt" | tail -4
}

for part in $parts; do
  case $part in
    cold)
      WARP_CACHE_PATH=$cache/one run cold_1rank "$py" train/ppo.py --task Reach --max-iterations 1 --eval-envs 16 \
        --log-dir "$cache/runs"
      WARP_CACHE_PATH=$cache/two run cold_2rank "${torchrun[@]}" train/ppo.py --task Reach --distributed \
        --max-iterations 1 --eval-envs 16 --log-dir "$cache/runs"
      WARP_CACHE_PATH=$cache/two run warm_2rank "${torchrun[@]}" train/ppo.py --task Reach --distributed \
        --max-iterations 1 --eval-envs 16 --log-dir "$cache/runs" ;;
    state)
      run state_1gpu_150it "$py" train/ppo.py --task Reach --max-iterations 150 --log-dir "$cache/runs"
      run state_2gpu_75it "${torchrun[@]}" train/ppo.py --task Reach --distributed --max-iterations 75 \
        --log-dir "$cache/runs"
      run state_2gpu_150it "${torchrun[@]}" train/ppo.py --task Reach --distributed --max-iterations 150 \
        --log-dir "$cache/runs" ;;
    rgb)
      run rgb_1gpu_150it "$py" train/ppo.py --task Reach --obs rgb --max-iterations 150 --log-dir "$cache/runs"
      run rgb_2gpu_75it "${torchrun[@]}" train/ppo.py --task Reach --obs rgb --distributed --max-iterations 75 \
        --log-dir "$cache/runs" ;;
    same)
      run state_2gpu_75it_same "${torchrun[@]}" train/ppo.py --task Reach --distributed --same-global-minibatch \
        --max-iterations 75 --log-dir "$cache/runs"
      run rgb_2gpu_75it_same "${torchrun[@]}" train/ppo.py --task Reach --obs rgb --distributed \
        --same-global-minibatch --max-iterations 75 --log-dir "$cache/runs" ;;
    deformable)
      run tm_state_1gpu_150it "$py" train/ppo.py --task TissueManipulation --max-iterations 150 --log-dir "$cache/runs"
      run tm_state_2gpu_75it "${torchrun[@]}" train/ppo.py --task TissueManipulation --distributed \
        --max-iterations 75 --log-dir "$cache/runs" ;;
    *) echo "unknown part $part (cold, state, rgb, same, deformable)"; exit 2 ;;
  esac
done
