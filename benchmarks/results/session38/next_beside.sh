#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1),
# written in the thirty-eighth session, in order of need (~15 min), then the learning queue JOBS until DEADLINE:
# 1. GPU tests of the thirty-eighth session's changes: the multipliers allocated where iterations is set directly,
#    profile_step's device gaps, LigatingLoop on its new default (one rotation iteration);
# 2. where LigatingLoop's step goes beyond its kernels (45.8 ms against 39.0 ms of device kernels last lease; 0.6 ms
#    for RopeThreading): profile_step --profiler torch --graph now lists the device's idle gaps with the kernels beside
#    them; LigatingLoop's step with and without the graph;
# 3. ThreadInHole on its new GPU default (its thread's chain by PCR, 164.4k against 160.2k last lease; its continuous
#    expert 256 / 256 per configuration on it) against the serial walk, and its discrete expert on it;
# 4. a 10^7-step soak of LigatingLoop on its new default (5 x 10^6 ran clean in the quick call);
# 5. the step of the six tasks whose #17 / #18 targets are open, same call (expert, 4,096 envs).
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3_next.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session38
out=/tmp/r/beside39
mkdir -p "$out"
new=/tmp/site:$PWD
. train/device/beside_lib.sh  # bench, run_queue
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_physics_basic.py tests/test_train_and_bench.py \
  tests/test_ligating_loop.py -k "iterations_set or profile_step or device_gaps or sag or slots or pins" \
  --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
for task in LigatingLoop RopeThreading ThreadInHole RopeCutting; do
  PYTHONPATH=$new timeout 240 python3 benchmarks/profile_step.py --task "$task" --device "$dev" --num-envs "$n" \
    --steps 5 --warmup 10 --profiler torch --graph --top 40 --out "$out/tprofile_$task.json" \
    > "$out/tprofile_$task.txt" 2>&1
  echo "tprofile_$task rc=$? $(grep -A3 'device per env step' "$out/tprofile_$task.txt" | tr '\n' ' ' | cut -c1-400)"
done
bench ll LigatingLoop expert
bench ll_nograph LigatingLoop expert --no-graph
bench tih ThreadInHole expert
bench tih_serial ThreadInHole expert --set chain_solver='"thomas"'
PYTHONPATH=$new timeout 300 python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" --num-envs 256 \
  --action-types DISCRETE --config configuration=normal --config configuration=flexible \
  --config configuration=inverted --out "$out/expert_tih_pcr.jsonl" > "$out/expert_tih_pcr.txt" 2>&1
echo "expert_tih_pcr rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih_pcr.jsonl" | tr '\n' ' ')"
PYTHONPATH=$new timeout 240 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks LigatingLoop --action-types CONTINUOUS --out "$out/soak_ll.jsonl" > "$out/soak_ll.txt" 2>&1
echo "soak_ll rc=$? $(tail -1 "$out/soak_ll.txt" | cut -c1-300)"
for task in RopeCutting PrecisionCutting TissueDissection RopeThreading; do
  bench "step_$task" "$task" expert
done
run_queue "${JOBS:-$d/next_jobs_gpu3_next.txt}" "${DEADLINE:-1400}"
