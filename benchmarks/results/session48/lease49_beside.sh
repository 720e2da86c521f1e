#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-eighth session), run as queue.sh's BESIDE on the second H200 of an
# nvidia-h200-x2 lease (DEVICE=cuda:1; the queue trains on cuda:0) or, on one H200, before the queue's runs (DEVICE
# cuda:0), each item skipped once DEADLINE (s, default 330) has passed:
# 1. RopeThreading with each substep's closing attachment pass and particle contact in the next substep's rod launch
#    (World.contact_in_rod_launch, the forty-eighth session's default: 28 launches per physics step instead of 45;
#    untimed) against their own launches, that fused launch at 96 registers (84 uncapped) against its cap of 64, STATE
#    and RGB 64x64 (#18's RGB 200k: 190.2k at 4d776a2, their own launches);
# 2. RopeThreading at 9 and 8 substeps per physics step against its 10, STATE and RGB. CPU, forty-eighth session: the
#    held rope's fitted bending within 6.0 / 2.6 % (9) and 6.3 / 2.3 % (8) of E I against 5.8 / 2.8 % (10), root
#    slope at node 15 -1.92 / -2.10 deg against -1.80 (80 substeps: -1.25), no tunnelling through the eye at full
#    speed at either, the continuous expert 32 / 32, 29 / 32, 32 / 32 (base, two eyes, bimanual) at 8 against
#    32 / 27 / 32 at 10;
# 3. the RopeThreading continuous experts at 10 (the fused contact on a GPU), 9 and 8 substeps on 256 first episodes
#    (base, two eyes, bimanual; at 10 before: 99.8 / 91.5 / 98.8 % on 1,024);
# 4. the other tasks whose particle contact is now a wp.func called by its kernel (LigatingLoop, ThreadInHole,
#    GraspLiftAndTouch; 103.2k / 348.4k / 297.4k before) and the GPU tests of the fused launch and the rope;
# then the learning queue JOBS (session48/lease49_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1500).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench_variants, run_queue
DEADLINE=${DEADLINE:-330} beside_init /tmp/r/beside49
in_time rt && bench_variants rt RopeThreading expert "fused=" "own=--contact-in-rod-launch off" \
  "fused96=--max-registers contact_predict_and_solve_rods_fused=96" "s9=--set physics_substeps=9" \
  "s8=--set physics_substeps=8" "rgb_fused=--obs RGB" "rgb_own=--obs RGB --contact-in-rod-launch off" \
  "rgb_s9=--obs RGB --set physics_substeps=9" "rgb_s8=--obs RGB --set physics_substeps=8"
two_eyes='eyes=[[0.06,0.01,0,90],[0.01,0.01,0,90]]'
for s in 10 9 8; do
  in_time "expert_s$s" && {
    PYTHONPATH=$new timeout 150 python3 benchmarks/expert_success.py --task RopeThreading --device "$dev" \
      --num-envs 256 --action-types CONTINUOUS --config physics_substeps=$s --config physics_substeps=$s "$two_eyes" \
      --config physics_substeps=$s bimanual=true --out "$out/expert_rt_s$s.jsonl" > "$out/expert_rt_s$s.txt" 2>&1
    echo "expert_s$s rc=$? $(grep -o '"overrides": {[^}]*}, "world": {}, "action_type": "[A-Z]*"\|"success_rate": [0-9.]*' \
      "$out/expert_rt_s$s.jsonl" | paste -sd' ' | cut -c1-900)"
  }
done
in_time others && for task in LigatingLoop ThreadInHole GraspLiftAndTouch; do bench "other_$task" "$task" expert; done
if in_time pytest; then
  PYTHONPATH=$new timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_contact.py \
    tests/test_rope_threading.py -k "rod_launch or tunnel or bending" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-benchmarks/results/session48/lease49_jobs_beside.txt}" "${QUEUE_DEADLINE:-1500}"
