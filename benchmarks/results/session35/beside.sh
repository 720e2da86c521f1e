#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~12 min
# of checks in order of need, then the learning queue JOBS until DEADLINE seconds after this script started:
# 1. the GPU tests of the thirty-fifth session's changes: ThreadInHole's register cap (its sag tests), the bench's kept
#    task caps, LigatingLoop's sag with the lagged XPBD cavity, TissueDissection's tests on its new default;
# 2. ThreadInHole's new default (its lagged vertex sweep capped at 64 registers by the task; the quick lease timed the
#    cap as a bench option, 143.1k against 134.6k) against the same kernel at 255 (uncapped: it needs 80), same call;
# 3. TissueDissection's 10^7-step random-action soak on its new default (the rotations once per sweep; #17 asks one per
#    task; the quick lease had no time for it);
# 4. caps of the two one-warp-per-env kernels at 71 / 72 registers (1.11 waves of 4,096 envs) at 64 (one wave):
#    RopeThreading, RopeCutting, LigatingLoop, ThreadInHole, TissueDissection; and of RopeCutting's rope contact and
#    TissueDissection's outcode triangle sweep (benchmarks/kernel_resources.py --blocks 4096);
# 5. profiles: LigatingLoop with the lagged cavity (23.4k against 80.2k in the quick lease, same call; on the CPU its
#    steps grow costlier as the loop presses on the stiffer cavity) against its default, and ThreadInHole (where its 143k go; #18 asks 300k).
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session35
out=/tmp/r/beside35
mkdir -p "$out"
new=/tmp/site:$PWD
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_thread_in_hole.py tests/test_train_and_bench.py \
  tests/test_ligating_loop.py -k "sag or register_caps" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
PYTHONPATH=$new timeout 600 python3 -m pytest -q -p no:cacheprovider tests/test_tissue_dissection.py --device "$dev" \
  > "$out/pytest_td_cuda.txt" 2>&1
echo "pytest td rc=$? $(tail -1 "$out/pytest_td_cuda.txt")"
bench() {  # NAME TASK OBS [bench_env.py options...]
  local name=$1 task=$2 obs=$3
  shift 3
  PYTHONPATH=$new python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 --obs "$obs" \
    --policy expert "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
bench tih_default ThreadInHole STATE
bench tih_uncapped ThreadInHole STATE --max-registers solve_vertices_fused=255
bench tih_default_again ThreadInHole STATE
PYTHONPATH=$new python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks TissueDissection --action-types CONTINUOUS --out "$out/soak_td.jsonl" > "$out/soak_td.txt" 2>&1
echo "soak rc=$? $(tail -2 "$out/soak_td.txt" | tr '\n' ' ' | cut -c1-300)"
# one-warp-per-env kernels between 64 and 72 registers (sm_90) take 28 blocks per SM, so 4,096 envs need 1.11 waves
# on 132 SMs; at 64 all fit one (spill frames 16 and 32 B): solve_rods_fused (71 registers) and
# pose_shapes_and_tools (72), each pair in the same call
bench rt_default RopeThreading STATE
bench rt_rods64 RopeThreading STATE --max-registers solve_rods_fused=64
bench rc_default RopeCutting STATE
bench rc_rods64 RopeCutting STATE --max-registers solve_rods_fused=64
bench ll_default LigatingLoop STATE
bench ll_rods64 LigatingLoop STATE --max-registers solve_rods_fused=64
bench tih_both64 ThreadInHole STATE --max-registers solve_rods_fused=64 pose_shapes_and_tools=64
bench td_default TissueDissection STATE
bench td_pose64 TissueDissection STATE --max-registers pose_shapes_and_tools=64
# two more one-warp-per-env kernels into one wave at 64, with larger spill frames: RopeCutting's rope contact (96
# registers, 1.48 waves; 168 B) and TissueDissection's outcode triangle sweep (120, 1.83 waves; 152 B)
bench rc_seg64 RopeCutting STATE --max-registers collide_segment_colors=64
bench td_outcodes64 TissueDissection STATE --max-registers collide_triangle_outcodes=64
prof() {  # NAME TASK [profile_step.py options...]
  local name=$1 task=$2
  shift 2
  PYTHONPATH=$new python3 benchmarks/profile_step.py --task "$task" --device "$dev" --num-envs "$n" --steps 5 \
    --warmup 10 "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(head -1 "$out/$name.txt")"
}
prof profile_ll LigatingLoop
prof profile_ll_sweep LigatingLoop --set cavity_rotation_update='"sweep"'
prof profile_tih ThreadInHole
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
