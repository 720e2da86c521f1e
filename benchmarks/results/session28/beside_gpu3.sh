#!/usr/bin/env bash
# GPU 3 of the next x4 lease (GPU 1 of an x2 lease: DEVICE=cuda:1), from the code copy (queue.sh's BESIDE):
# 1. the outcode triangle sweep (new, bit-identical on the CPU) against the fused one: its GPU tests, then
#    TissueDissection (STATE, RGB 64x64 and a profile), PrecisionCutting and ThreadInHole, expert, STATE;
# 2. RopeCutting's step at 6 / 5 / 4 Newton steps of its rope solve (4 settle on the CPU too);
# 3. RopeCutting's cut reset against its uncut one (1.155 on an H200 in the twenty-eighth session, with kernel sums
#    0.512 / 0.460 ms and the profiled walls the other way round, 1.578 / 1.706 ms): 30 repeats in alternating order
#    (bench_reset.py since the twenty-eighth session), with sofa_env's layout rule and with min_rope_distance=0 (every
#    rope's first draw accepted: the layout's rejection draws, whose cost is the slowest of 4,096 envs, drop out);
# 4. PrecisionCutting's step (expert, STATE) over the cloth's substeps x Newton steps (steady centre sag, CPU, 5 s
#    after reset: converged 7.6 mm; 8 x 2, the default, 9.7; 8 x 1 10.4; 16 x 1 8.5; 12 x 1 9.3; 4 x 2 11.4; 32 x 1
#    7.8): what each costs against the 100k target;
# 5. register caps of the kernels that lead the step profiles (TissueDissection, PrecisionCutting, ThreadInHole,
#    LigatingLoop; expert, STATE, each against its baseline in the same call);
# 6. kernel profiles of ThreadInHole, RopeThreading and LigatingLoop (issue #18's speeds; the profiles on record are
#    many sessions old);
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session28
out=/tmp/r/beside28
mkdir -p "$out"
# the outcode triangle sweep (ContactSystem.triangle_sweep = "outcodes", new: the fused sweep's box cull read from
# per-particle outcodes in shared memory, bit-identical on the CPU) against the fused one, on the GPU tests first
python3 -m pytest -q -p no:cacheprovider tests/test_contact.py tests/test_physics_basic.py \
  -k "fused or outcode or register" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
for task in TissueDissection PrecisionCutting ThreadInHole; do
  for sweep in fused outcodes; do
    python3 benchmarks/bench_env.py --task $task --device "$dev" --num-envs "$n" --seconds 3 --obs STATE \
      --policy expert --triangle-sweep $sweep --out "$out/sweep_${task}_$sweep.json" > "$out/sweep_${task}_$sweep.txt" 2>&1
    echo "sweep $task $sweep rc=$? $(tail -1 "$out/sweep_${task}_$sweep.txt")"
  done
done
for sweep in fused outcodes; do
  python3 benchmarks/bench_env.py --task TissueDissection --device "$dev" --num-envs "$n" --seconds 3 --obs RGB \
    --policy expert --triangle-sweep $sweep --out "$out/sweep_td_rgb_$sweep.json" > "$out/sweep_td_rgb_$sweep.txt" 2>&1
  echo "sweep TissueDissection RGB $sweep rc=$? $(tail -1 "$out/sweep_td_rgb_$sweep.txt")"
done
python3 benchmarks/profile_step.py --task TissueDissection --device "$dev" --num-envs "$n" --warmup 60 --steps 20 \
  --triangle-sweep outcodes --out "$out/profile_td_outcodes.json" > "$out/profile_td_outcodes.txt" 2>&1
echo "profile_td_outcodes rc=$?"; head -8 "$out/profile_td_outcodes.txt"
# RopeCutting's rope solve at 6 Newton steps per sweep (the default) against 4 and 5: on the CPU (one rope, 40
# substeps) 4 and more settle to the taut-string closed form within 0.2 % after 5-20 mm bumps in y and z, 3 does not
# after 20 mm (the chain solve is 63 % of RopeCutting's step)
for newton in 6 5 4; do
  python3 benchmarks/bench_env.py --task RopeCutting --device "$dev" --num-envs "$n" --seconds 3 --obs STATE \
    --policy expert --set rope_newton_steps=$newton --out "$out/rc_newton$newton.json" > "$out/rc_newton$newton.txt" 2>&1
  echo "rc_newton$newton rc=$? $(tail -1 "$out/rc_newton$newton.txt")"
done
for layout in sofa free; do
  extra=""
  [ "$layout" = free ] && extra="min_rope_distance=0"
  python3 benchmarks/bench_reset.py --tasks RopeCutting --device "$dev" --num-envs "$n" --repeats 30 \
    --set num_ropes_to_cut=3 $extra --out "$out/reset_rc_$layout.json" > "$out/reset_rc_$layout.txt" 2>&1
  echo "reset_rc_$layout rc=$? $(tail -1 "$out/reset_rc_$layout.txt")"
done
for cfg in 8x2 8x1 16x1 12x1 4x2 32x1; do
  sub=${cfg%x*}; newton=${cfg#*x}
  python3 benchmarks/bench_env.py --task PrecisionCutting --device "$dev" --num-envs "$n" --seconds 3 --obs STATE \
    --policy expert --set physics_substeps=$sub cloth_newton_steps=$newton --out "$out/pc_$cfg.json" \
    > "$out/pc_$cfg.txt" 2>&1
  echo "pc_$cfg rc=$? $(tail -1 "$out/pc_$cfg.txt")"
done
# register caps (World.max_registers, bench_env.py --max-registers; launching.register_capped) of the latency-bound
# kernels that lead the profiles: TissueDissection's triangle contact (7.28 ms of its 21.13 ms STATE step: 46 colours
# in series, one 32-lane block per env), its fused tet sweep (5.85) and particle contact (1.94); PrecisionCutting's
# cloth chains (capped at 96 since the twelfth session's measurement); ThreadInHole's triangle
# contact and LigatingLoop's surface contact. "none" is each task's baseline in the same call
for spec in "TissueDissection none" "TissueDissection collide_triangle_colors=64" \
    "TissueDissection collide_triangle_colors=96" "TissueDissection solve_tets_fused=96" \
    "TissueDissection solve_tets_fused=64" "TissueDissection collide_particles=64" \
    "PrecisionCutting solve_chains=64" "ThreadInHole none" "ThreadInHole collide_triangle_colors=64" \
    "LigatingLoop none" "LigatingLoop collide_surface=64"; do
  set -- $spec
  caps=""
  [ "$2" = none ] || caps="--max-registers $2"
  name="caps_$1_${2%%=*}_${2#*=}"  # no "=" in the file names (the device tool returns plain names only)
  python3 benchmarks/bench_env.py --task $1 --device "$dev" --num-envs "$n" --seconds 3 --obs STATE --policy expert \
    $caps --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "caps $1 $2 rc=$? $(tail -1 "$out/$name.txt")"
done
for task in ThreadInHole RopeThreading LigatingLoop; do
  python3 benchmarks/profile_step.py --task $task --device "$dev" --num-envs "$n" --warmup 20 --steps 10 \
    --out "$out/profile_$task.json" > "$out/profile_$task.txt" 2>&1
  echo "profile_$task rc=$?"; head -8 "$out/profile_$task.txt"
done
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
