#!/usr/bin/env bash
# The forty-eighth session's GPU checks (session 47's, unchanged), run as queue.sh's BESIDE on the second H200 of an
# nvidia-h200-x2 lease (DEVICE=cuda:1; the queue trains on cuda:0), each item skipped once DEADLINE (s, default 300)
# has passed:
# 1. ThreadInHole on HEAD (its held hole now also keeps its surface's contact boxes: ~0.95 ms per env step of leaf and
#    super-leaf boxes in the profile; the forty-seventh session's quick call: 341.9k held, 217.3k unheld), STATE, RGB
#    and unheld, and a profile;
# 2. how many envs end a step held on the GPU (benchmarks/tet_hold.py, expert and random actions, 4,096 envs): the
#    held vertex sweep still cost 1.49 ms of its unheld 9.59 in the forty-seventh session's profile, as if ~15 % of the
#    envs were solved, where the CPU's expert ends 2 % of env steps awake (those just reset);
# 3. GPU tests of the hold (a pressed block against the unheld solve; the hole's boxes kept while held), after
# 4. a probe of the particle contact launch (below);
# then the learning queue JOBS (session48/next_jobs_beside.txt) until QUEUE_DEADLINE (s, default 1450): PrecisionCutting's fixed
# sine with the paper's 4 stacked state frames (~1,076 s on an H200), while cuda:0 trains the random one.
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS, DEADLINE and QUEUE_DEADLINE override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench_variants, profile, run_queue
DEADLINE=${DEADLINE:-300} beside_init /tmp/r/beside48
d=benchmarks/results/session47  # its probes
in_time tih && bench_variants tih ThreadInHole expert "tih=" "tih_nohold=--set hole_hold_speed=0" "rgb_tih=--obs RGB"
in_time profile && profile ThreadInHole
# RopeThreading RGB with its tube written a thread per ring vertex (generate_tube: 0.27 ms per frame before; the
# forty-seventh session's quick call: 188.3k) and its profile
in_time rt && bench_variants rt RopeThreading expert "rgb_rt=--obs RGB"
in_time profile_rt && profile RopeThreading RopeThreading_RGB --set observation_type=RGB
for policy in expert random; do
  in_time "hold_$policy" && {
    PYTHONPATH=$new timeout 120 python3 benchmarks/tet_hold.py --task ThreadInHole --device "$dev" --num-envs "$n" \
      --steps 100 --policy $policy --out "$out/hold_$policy.json" > "$out/hold_$policy.txt" 2>&1
    echo "hold_$policy rc=$? $(tail -1 "$out/hold_$policy.txt" | cut -c1-300)"
  }
done
# 4. where the particle contact launch's time goes (RopeThreading 5.2 ms per env step, ThreadInHole 1.5, LigatingLoop
#    3.7): one recorded launch replayed with variants (loads only, culls only, no friction, no reports), CUDA events
for task in RopeThreading ThreadInHole LigatingLoop; do
  in_time "contact_$task" && {
    PYTHONPATH=$new timeout 100 python3 $d/probes/contact_probe.py $task "$n" "$out/contact_$task.json" "$dev" \
      > "$out/contact_$task.txt" 2>&1
    echo "contact_$task rc=$? $(grep -E '^(as_is|cp_)' "$out/contact_$task.txt" | tr '\n' ' ')"
  }
done
if in_time pytest; then
  PYTHONPATH=$new timeout 150 python3 -m pytest -q -p no:cacheprovider tests/test_tet_hold.py \
    "tests/test_thread_in_hole.py::test_held_hole_keeps_its_contact_boxes" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-benchmarks/results/session48/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1450}"
