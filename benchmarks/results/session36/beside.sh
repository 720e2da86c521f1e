#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~12 min
# of checks in order of need, then the learning queue JOBS until DEADLINE seconds after this script started. OLD (the
# thirty-sixth session's quick-lease code, dd0b651, carried as .device/small/old) against the new code, same call:
# 1. the GPU tests of the thirty-sixth session's changes: LigatingLoop's attachment slots a thread per slot (against
#    the walk, 1e-6 m) and its pins, the packed XPBD colours, the fused tet sweeps, the particle contact;
# 2. LigatingLoop (#18 asks 100k; 86.4k at dd0b651): the new default (its attachment slots a thread each; the particle
#    contact reading a particle's start position and pass-through mask only where a shape is near) against dd0b651,
#    and with the cavity's colours packed (cavity_tet_colors="packed": 72 passes per sweep instead of 78);
#    ThreadInHole (with it, its capped vertex sweep spilling 32 B instead of 64) and GraspLiftAndTouch (the contact
#    change alone) against dd0b651, TissueDissection
#    (with it, its lagged XPBD tet sweep at 96 registers instead of 114: the corners re-read from the tile);
#    its cavity's fused XPBD sweep (127 registers, 1.94 waves of 4,096 one-warp blocks; 48.7 % of its kernel time)
#    capped at 64 / 80 / 96;
# 3. LigatingLoop's expert (256 first episodes, stiff and soft) on the default and with the packed colours (on the CPU
#    the soft loop's expert closed 6 of 8 with them against 8 of 8; stiff 8 of 8 either way), a 10^7-step soak;
# 4. the contact sweeps' caps together with this session's rods / pose caps: RopeCutting's collide_segment_colors and
#    TissueDissection's collide_triangle_outcodes at 64 (each +0.7 / +0.2 % alone);
# 5. RopeThreading and RopeCutting on the new defaults against 555e7ee's figures (the quick lease had no time), and
#    a LigatingLoop profile on the new default.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session36
out=/tmp/r/beside36
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_ligating_loop.py tests/test_colour_packing.py \
  tests/test_fused_tets.py tests/test_contact.py -k "slots or pins or closing or packs or packed or fused or vertex or \
  particle" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME TASK PYTHONPATH [bench_env.py options...]
  local name=$1 task=$2 path=$3
  shift 3
  PYTHONPATH=$path python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy expert "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
bench ll_old LigatingLoop "$old"
bench ll_new LigatingLoop "$new"
bench ll_packed LigatingLoop "$new" --set cavity_tet_colors='"packed"'
bench ll_new_again LigatingLoop "$new"
bench tih_old ThreadInHole "$old"
bench tih_new ThreadInHole "$new"
bench glt_old GraspLiftAndTouch "$old"
bench glt_new GraspLiftAndTouch "$new"
bench ll_tets64 LigatingLoop "$new" --max-registers solve_tets_fused=64
bench ll_tets80 LigatingLoop "$new" --max-registers solve_tets_fused=80
bench ll_tets96 LigatingLoop "$new" --max-registers solve_tets_fused=96
PYTHONPATH=$new timeout 420 python3 benchmarks/expert_success.py --task LigatingLoop --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS --config loop_stiffness=stiff --config loop_stiffness=soft \
  --config "loop_stiffness=stiff cavity_tet_colors=packed" --config "loop_stiffness=soft cavity_tet_colors=packed" \
  --out "$out/expert_ll.jsonl" > "$out/expert_ll.txt" 2>&1
echo "expert rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_ll.jsonl" | tr '\n' ' ')"
PYTHONPATH=$new timeout 300 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks LigatingLoop --action-types CONTINUOUS --out "$out/soak_ll.jsonl" > "$out/soak_ll.txt" 2>&1
echo "soak rc=$? $(tail -1 "$out/soak_ll.txt" | cut -c1-300)"
bench rc_new RopeCutting "$new"
bench rc_seg64 RopeCutting "$new" --max-registers collide_segment_colors=64
bench td_old TissueDissection "$old"
bench td_new TissueDissection "$new"
bench td_outcodes64 TissueDissection "$new" --max-registers collide_triangle_outcodes=64
bench rt_new RopeThreading "$new"
PYTHONPATH=$new python3 benchmarks/profile_step.py --task LigatingLoop --device "$dev" --num-envs "$n" --steps 5 \
  --warmup 10 --out "$out/profile_ll.json" > "$out/profile_ll.txt" 2>&1
echo "profile_ll rc=$? $(head -1 "$out/profile_ll.txt")"
jobs=${JOBS:-$d/next_jobs_gpu3.txt}
grep -qv '^#' "$jobs" || { echo "no jobs in $jobs"; exit 0; }
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "$jobs" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
