#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-eighth session), run as queue.sh's BESIDE on the second H200 of an
# nvidia-h200-x2 lease (DEVICE=cuda:1; the queue trains on cuda:0) or, on one H200, before the queue's runs (DEVICE
# cuda:0), each item skipped once DEADLINE (s, default 300) has passed:
# 1. the particle contact probe with its launches timed inside a CUDA graph (the forty-eighth session's events from
#    Python also timed the host's launch packing: a 38 us floor for 409,600 and 3.3M threads alike);
# 2. RopeThreading at 9 and 8 substeps per physics step against its 10, STATE and RGB 64x64 (#18's RGB 200k: 190.2k at
#    10). CPU, forty-eighth session: the held rope's fitted bending within 6.0 / 2.6 % (9) and 6.3 / 2.3 % (8) of E I
#    against 5.8 / 2.8 % (10), root slope at node 15 -1.92 / -2.10 deg against -1.80 (80 substeps: -1.25), no
#    tunnelling through the eye at full speed at either, the continuous expert 32 / 32, 29 / 32, 32 / 32 (base, two
#    eyes, bimanual) at 8 against 32 / 27 / 32 at 10;
# 3. the RopeThreading experts at 9 and 8 substeps on 256 first episodes (base, two eyes, bimanual; C and D);
# then the learning queue JOBS (session48/lease49_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1450).
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench_variants, run_queue
DEADLINE=${DEADLINE:-300} beside_init /tmp/r/beside49
probes=benchmarks/results/session47/probes
for task in RopeThreading LigatingLoop; do
  in_time "contact_$task" && {
    PYTHONPATH=$new timeout 100 python3 $probes/contact_probe.py $task "$n" "$out/contact_$task.json" "$dev" \
      > "$out/contact_$task.txt" 2>&1
    echo "contact_$task rc=$? $(grep -E '^(as_is|cp_)' "$out/contact_$task.txt" | tr '\n' ' ')"
  }
done
in_time rt && bench_variants rt RopeThreading expert "s10=" "s9=--set physics_substeps=9" \
  "s8=--set physics_substeps=8" "rgb_s10=--obs RGB" "rgb_s9=--obs RGB --set physics_substeps=9" \
  "rgb_s8=--obs RGB --set physics_substeps=8"
two_eyes='eyes=[[0.06,0.01,0,90],[0.01,0.01,0,90]]'
for s in 9 8; do
  in_time "expert_s$s" && {
    PYTHONPATH=$new timeout 150 python3 benchmarks/expert_success.py --task RopeThreading --device "$dev" \
      --num-envs 256 --config physics_substeps=$s --config physics_substeps=$s "$two_eyes" \
      --config physics_substeps=$s bimanual=true --out "$out/expert_rt_s$s.jsonl" > "$out/expert_rt_s$s.txt" 2>&1
    echo "expert_s$s rc=$? $(grep -o '"overrides": {[^}]*}, "world": {}, "action_type": "[A-Z]*"\|"success_rate": [0-9.]*' \
      "$out/expert_rt_s$s.jsonl" | paste -sd' ' | cut -c1-900)"
  }
done
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-benchmarks/results/session48/lease49_jobs_beside.txt}" "${QUEUE_DEADLINE:-1450}"
