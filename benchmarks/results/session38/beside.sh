#!/usr/bin/env bash
# The GPU beside the thirty-eighth session's lease queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1):
# the thirty-seventh session's planned checks (results/session37/next_lease.md; its plan's script, superseded by this
# one, is removed; this session's first try of the lease was refused, the wheel's parts too large), with first, same call, PrecisionCutting (#17 asks 100k; 26.1k)
# with its cloth's chain sets solved in shared memory (World.chain_solver "shared", kernels/chains_shared.py: a block
# per env walks the 40 x 40 cloth's three families in one launch per sweep, every dependent load of the walk from
# shared memory; bit-identical to the serial walk on the CPU) at 64 / 40 / 32 lanes per block against the serial walk
# (its default), and the shared solve's GPU tests. Then, as planned there:
# ~20 min of checks in order of need, then the learning queue JOBS until DEADLINE seconds after this script started.
# OLD (the thirty-seventh session's lease code, b9ad86d, carried as .device/small/old; queue.sh now copies it next to
# the code this runs from) against the new code, same call:
# 1. GPU tests of the thirty-seventh session's changes: ThreadInHole (its hole's rotations refreshed once per physics
#    step, the sag at 1 and 4), the register caps' defaults, the fused tets, LigatingLoop;
# 2. LigatingLoop (#18 asks 100k; 89.3k at b9ad86d): the new default (its cavity sweep capped at 96) against b9ad86d,
#    one rotation extraction iteration per projection (cavity_rotation_iterations=1: the sweep is bound by its
#    instruction issue; CPU: sag 12.33 against 12.57 mm, expert stiff / soft 8 / 8 each, soft mean length 98 against
#    132), the packed colours, both; the step replayed on the best;
# 3. LigatingLoop's expert (256 first episodes, stiff and soft) on the default, the packed colours, one iteration and
#    both (the packed colours' GPU expert did not run last time: each --config was one quoted word; CPU, 8 first
#    episodes: packed 8 / 6, one iteration 8 / 8, both 8 / 7, stiff / soft);
# 4. ThreadInHole on its new default against b9ad86d (hole_rotation_refresh 1 there; 151.1k -> 159.4k in the quick
#    lease) and on the other chain solves, its experts (256 first episodes per configuration) and a 10^7-step soak;
#    PrecisionCutting against b9ad86d (the serial chain walk, ~80 % of its step, loads a link's new node one link
#    ahead), also at register caps 128 / 160 (timed before the experts);
# 5. RopeCutting and TissueDissection on their new caps against b9ad86d; RopeThreading against b9ad86d; a LigatingLoop
#    profile with one iteration. Every rod task's new code also predicts its particles and segments in one launch per
#    substep (World.integrate_together; RopeThreading 99 launches fewer per env step, LigatingLoop 38, ThreadInHole 30).
# 6. PyTorch's profiler over LigatingLoop's and RopeThreading's replayed graphs (profile_step.py --profiler torch
#    --graph): every device kernel, Warp's native BVH refits and memsets included.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session38
out=/tmp/r/beside38
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
[ -d "$PWD/.device/small/old/lapwarp" ] || echo "no old tree at $PWD/.device/small/old: the old runs will fail"
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_thread_in_hole.py tests/test_physics_basic.py \
  tests/test_fused_tets.py tests/test_ligating_loop.py -k "sag or register or fused or unknown or slots or pins" \
  --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME TASK PYTHONPATH POLICY [bench_env.py options...]
  local name=$1 task=$2 path=$3 policy=$4
  shift 4
  PYTHONPATH=$path python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy "$policy" "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
# the shared-memory chain solve first (this session's), its GPU tests, then the serial walk in the same call
PYTHONPATH=$new timeout 300 python3 -m pytest -q -p no:cacheprovider tests/test_chains_shared.py --device "$dev" \
  > "$out/pytest_shared.txt" 2>&1
echo "pytest_shared rc=$? $(tail -1 "$out/pytest_shared.txt")"
bench pc_serial PrecisionCutting "$new" expert
bench pc_shared64 PrecisionCutting "$new" expert --set chain_solver='"shared"' --chain-lanes 64
bench pc_shared40 PrecisionCutting "$new" expert --set chain_solver='"shared"' --chain-lanes 40
bench pc_shared32 PrecisionCutting "$new" expert --set chain_solver='"shared"' --chain-lanes 32
bench ll_old LigatingLoop "$old" expert
bench ll_new LigatingLoop "$new" expert
bench ll_iter1 LigatingLoop "$new" expert --set cavity_rotation_iterations=1
bench ll_packed LigatingLoop "$new" expert --set cavity_tet_colors='"packed"'
bench ll_packed_iter1 LigatingLoop "$new" expert --set cavity_tet_colors='"packed"' cavity_rotation_iterations=1
bench ll_new_again LigatingLoop "$new" expert
bench ll_iter1_replay LigatingLoop "$new" replay --replay-steps 150 --set cavity_rotation_iterations=1
bench tih_old ThreadInHole "$old" expert
bench tih_new ThreadInHole "$new" expert
# its thread's chain solve (8.9 % of its kernels: one thread per env walks 12-20 links, one warp per SM) on the other
# solves (never timed on ThreadInHole): registers (RopeCutting's), pcr packs (LigatingLoop's), hybrid (RopeThreading's)
bench tih_registers ThreadInHole "$new" expert --set chain_solver='"registers"'
bench tih_pcr ThreadInHole "$new" expert --set chain_solver='"pcr"'
bench tih_hybrid ThreadInHole "$new" expert --set chain_solver='"hybrid"'
# the serial chain walk loading each link's new node one link ahead (software pipelining; PrecisionCutting's cloth
# spends ~80 % of its step in it, ThreadInHole's thread 8.9 %)
bench pc_old PrecisionCutting "$old" expert
bench pc_new PrecisionCutting "$new" expert
# (sm_90: the cloth's walk at its cap of 96 spills 336 B instead of 192 with the lookahead; uncapped 188 registers
# instead of 152)
bench pc_new_cap128 PrecisionCutting "$new" expert --max-registers solve_chains=128
bench pc_new_cap160 PrecisionCutting "$new" expert --max-registers solve_chains=160
PYTHONPATH=$new timeout 480 python3 benchmarks/expert_success.py --task LigatingLoop --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS --config loop_stiffness=stiff --config loop_stiffness=soft \
  --config loop_stiffness=stiff cavity_tet_colors=packed --config loop_stiffness=soft cavity_tet_colors=packed \
  --config loop_stiffness=stiff cavity_rotation_iterations=1 --config loop_stiffness=soft cavity_rotation_iterations=1 \
  --config loop_stiffness=stiff cavity_tet_colors=packed cavity_rotation_iterations=1 \
  --config loop_stiffness=soft cavity_tet_colors=packed cavity_rotation_iterations=1 \
  --out "$out/expert_ll.jsonl" > "$out/expert_ll.txt" 2>&1
echo "expert_ll rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_ll.jsonl" | tr '\n' ' ')"
PYTHONPATH=$new timeout 300 python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" --num-envs 256 \
  --action-types CONTINUOUS DISCRETE --config configuration=normal --config configuration=flexible \
  --config configuration=inverted --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
echo "expert_tih rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih.jsonl" | tr '\n' ' ')"
PYTHONPATH=$new timeout 240 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks ThreadInHole --action-types CONTINUOUS --out "$out/soak_tih.jsonl" > "$out/soak_tih.txt" 2>&1
echo "soak_tih rc=$? $(tail -1 "$out/soak_tih.txt" | cut -c1-300)"
bench rc_old RopeCutting "$old" expert
bench rc_new RopeCutting "$new" expert
bench td_old TissueDissection "$old" expert
bench td_new TissueDissection "$new" expert
bench rt_old RopeThreading "$old" expert
bench rt_new RopeThreading "$new" expert
PYTHONPATH=$new python3 benchmarks/profile_step.py --task LigatingLoop --device "$dev" --num-envs "$n" --steps 5 \
  --warmup 10 --set cavity_rotation_iterations=1 --out "$out/profile_ll_iter1.json" > "$out/profile_ll_iter1.txt" 2>&1
echo "profile_ll_iter1 rc=$? $(head -1 "$out/profile_ll_iter1.txt")"
# every device kernel of the replayed graph (PyTorch's profiler): where LigatingLoop's 45.8 ms step spends the ~6 ms
# that Warp's kernel timer (39.4 ms) does not see; RopeThreading's the same way
for task in LigatingLoop RopeThreading; do
  PYTHONPATH=$new timeout 240 python3 benchmarks/profile_step.py --task "$task" --device "$dev" --num-envs "$n" \
    --steps 5 --warmup 10 --profiler torch --graph --top 40 --out "$out/tprofile_$task.json" \
    > "$out/tprofile_$task.txt" 2>&1
  echo "tprofile_$task rc=$? $(head -1 "$out/tprofile_$task.txt")"
done
jobs=${JOBS:-$d/next_jobs_gpu3.txt}
grep -qv '^#' "$jobs" || { echo "no jobs in $jobs"; exit 0; }
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "$jobs" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
