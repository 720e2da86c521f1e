#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-fifth session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0) or beside a learning queue on the last GPU of a larger machine, in order of need, each item
# skipped once DEADLINE (s, default 1000) has passed, then the learning queue JOBS with the time left:
# 0. ThreadInHole (expert) on HEAD (its thread on the split register solve at 3e-4 m, the vertex sweep multiplying by
#    the tets' stiffnesses: 215.6k in the forty-fifth session's quick calls) alternated with two probes of its hole's
#    vertex sweep, which waits on its loads (a per-incidence form of its terms with half the arithmetic and more bytes
#    ran it 9.8 -> 12.7 ms per env step): p1 the env's stored rotations in a shared tile (8.6 KB per block: fewer
#    blocks per SM, each rotation a shared load instead of an L2 one), p2 each incidence's rotation loaded one
#    incidence ahead (a 56 B spill frame at the 64-register cap), p3 two incidences per loop iteration, their loads
#    issued together (123 registers uncapped, a 208 B frame at 64); HEAD and p3 also uncapped (p3 at 96 too); patches
#    in results/session45/probes, trees in .device/small/p1 .. p4;
#    then the surface contact kernel capped at 64 registers on ThreadInHole and LigatingLoop;
# 1. ThreadInHole's and RopeThreading's RGB 64x64 steps on HEAD and on p4 (the rasteriser's and shader's kernels at 48
#    registers), alternated; ThreadInHole's profile and a 10^7-step random-action soak on HEAD (#18's soak on its new default);
#    profiles of ThreadInHole's and RopeThreading's RGB steps (where the images' cost goes);
# 2. GPU tests of the per-vertex solve, the split and register chain solves, ThreadInHole and RopeCutting;
# 3. the six #17 / #18 tasks' steps on HEAD.
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS (next_jobs_beside.txt), DEADLINE (1000) and QUEUE_DEADLINE (1100) override.
set -u
. train/device/beside_lib.sh  # beside_init, in_time, bench, bench_on, profile, soak, run_queue
beside_init /tmp/r/beside46
d=benchmarks/results/session45
p1=/tmp/site:$PWD/.device/small/p1
p2=/tmp/site:$PWD/.device/small/p2
p3=/tmp/site:$PWD/.device/small/p3
p4=/tmp/site:$PWD/.device/small/p4
for round in a b; do
  in_time "tih_$round" || continue
  bench "tih_$round" ThreadInHole expert
  bench_on "$p1" "tih_p1_$round" ThreadInHole expert
  bench_on "$p2" "tih_p2_$round" ThreadInHole expert
  bench_on "$p3" "tih_p3_$round" ThreadInHole expert
done
in_time tih_uncapped && bench tih_uncapped ThreadInHole expert --max-registers solve_vertices_fused=255
in_time tih_p3_uncapped && bench_on "$p3" tih_p3_uncapped ThreadInHole expert --max-registers solve_vertices_fused=255
in_time tih_p3_96 && bench_on "$p3" tih_p3_96 ThreadInHole expert --max-registers solve_vertices_fused=96
# the surface contact kernel (77 registers, default blocks of 256: 3 blocks per SM) at 64 registers (4 blocks; a 40 B
# spill frame, sm_90; 72 would still hold 3): ThreadInHole's 2.3 ms of ~21, LigatingLoop's largest contact kernel
for round in a b; do
  in_time "surface64_$round" || continue
  bench "tih_surface64_$round" ThreadInHole expert --max-registers collide_surface=64
  bench "ll_$round" LigatingLoop expert
  bench "ll_surface64_$round" LigatingLoop expert --max-registers collide_surface=64
done
# p4: the rasteriser's and shader's kernels at 48 registers (53-55 uncapped: 4 blocks of 256 threads per SM, 5 at 48)
for round in a b; do
  in_time "rgb_$round" || continue
  bench "rgb_tih_$round" ThreadInHole expert --obs RGB
  bench_on "$p4" "rgb_tih_p4_$round" ThreadInHole expert --obs RGB
  bench "rgb_rt_$round" RopeThreading expert --obs RGB
  bench_on "$p4" "rgb_rt_p4_$round" RopeThreading expert --obs RGB
done
in_time profile_tih && profile ThreadInHole
in_time profile_ll && profile LigatingLoop  # its last profile is the twenty-ninth session's (100.4k now, #18's 100k)
# where RGB 64x64 adds its ~0.5 us per env step (#18's RGB 200k: ThreadInHole 195.6k, RopeThreading 180.9k)
in_time profile_tih_rgb && profile ThreadInHole ThreadInHole_RGB --set observation_type='"RGB"' image_shape='[64, 64]'
in_time profile_rt_rgb && profile RopeThreading RopeThreading_RGB --set observation_type='"RGB"' image_shape='[64, 64]'
in_time soak_tih && soak ThreadInHole 1e7
if in_time pytest; then
  PYTHONPATH=$new timeout 300 python3 -m pytest -q -p no:cacheprovider tests/test_vbd_lagged_terms.py \
    tests/test_fused_tets.py tests/test_chains_split.py tests/test_chains_registers.py tests/test_thread_in_hole.py \
    tests/test_rope_cutting.py --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
for task in PrecisionCutting TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1100}"
