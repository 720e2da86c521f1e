#!/usr/bin/env bash
# The next lease's GPU checks (written in the forty-fourth session), run as queue.sh's BESIDE on one H200 (an empty
# queue: DEVICE cuda:0) or beside a learning queue on the last GPU of a larger machine, in order of need, each item
# skipped once DEADLINE (s, default 1000) has passed, then the learning queue JOBS with the time left:
# 0. RopeCutting on its new default (the split register chain solve at 168 registers: 568.7k in the forty-fourth
#    session's quick calls), alternated with the split kernel's caps not tried yet (176 / 184 still fit one wave of
#    1,280 warps; 152 / 160), then its RGB 64x64 step, its profile and a 10^7-step random-action soak (#17's soak on the
#    new solve);
# 1. RopeCutting's split solve with a Newton tolerance (1e-7 / 1e-6 m: per chain, a block leaves once all stopped;
#    untimed), then ThreadInHole's thread (one 11-link chain per env, normal configuration) on the register solve (its
#    exact-length variant: no spill at 10 links, sm_90) and on the split one, without and with its 3e-4 m tolerance,
#    against its pcr default (204.9k-207.6k), alternated;
# 2. PrecisionCutting's cloth on the register solve with its equal rows and columns split (one point); GPU tests of the
#    split and register solves, RopeCutting's env;
# 3. the six #17 / #18 tasks' steps on the current defaults.
# DEVICE (cuda:0), NUM_ENVS (4096), JOBS (next_jobs_beside.txt), DEADLINE (1000) and QUEUE_DEADLINE (1100) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:0}
n=${NUM_ENVS:-4096}
deadline=${DEADLINE:-1000}
d=benchmarks/results/session44
out=/tmp/r/beside45
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
. train/device/beside_lib.sh  # bench, bench_old, run_queue
in_time() { [ $(( $(date +%s) - t0 )) -lt "$deadline" ] || { echo "deadline: skipped $*"; return 1; }; }
for round in a b; do
  in_time "rc_$round" || continue
  bench "rc_$round" RopeCutting expert
  for cap in 176 184 160 152; do
    bench "rc_split${cap}_$round" RopeCutting expert --max-registers solve_chains_split="$cap"
  done
done
in_time rgb_rc && bench rgb_RopeCutting RopeCutting expert --obs RGB
if in_time profile_rc; then
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task RopeCutting --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_RopeCutting.json" \
    > "$out/profile_RopeCutting.txt" 2>&1
  echo "profile_RopeCutting rc=$? $(head -4 "$out/profile_RopeCutting.txt" | tr '\n' ' ' | cut -c1-400)"
fi
if in_time soak_rc; then
  PYTHONPATH=$new timeout 300 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
    --tasks RopeCutting --action-types CONTINUOUS --out "$out/soak_RopeCutting.jsonl" > "$out/soak_RopeCutting.txt" 2>&1
  echo "soak_RopeCutting rc=$? $(tail -1 "$out/soak_RopeCutting.txt" | cut -c1-300)"
fi
for round in a b; do
  in_time "rc_tol_$round" || continue
  bench "rc_tol1e7_$round" RopeCutting expert --set rope_newton_tolerance=1e-7
  bench "rc_tol1e6_$round" RopeCutting expert --set rope_newton_tolerance=1e-6
done
for round in a b; do
  in_time "tih_$round" || continue
  bench "tih_$round" ThreadInHole expert
  bench "tih_registers_$round" ThreadInHole expert --set chain_solver='"registers"'
  bench "tih_split_$round" ThreadInHole expert --set chain_solver='"registers"' --register-split on
  bench "tih_split_tol_$round" ThreadInHole expert --set chain_solver='"registers"' thread_newton_tolerance=3e-4 \
    --register-split on
done
# PrecisionCutting's cloth on the register solve, its rows and columns (equal 39-link chains) split between two threads
# (20 links a thread), its diagonals (1-39 links) on the one-thread kernel: against the serial walk (27.3k)
in_time pc_split && bench pc_split PrecisionCutting expert --set chain_solver='"registers"' --register-split on
if in_time pytest; then
  PYTHONPATH=$new timeout 240 python3 -m pytest -q -p no:cacheprovider tests/test_chains_split.py \
    tests/test_chains_registers.py tests/test_rope_cutting.py --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
for task in PrecisionCutting TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
# ThreadInHole's profile on its defaults (the forty-fifth session's work on the hole's vertex sweep starts from it)
if in_time profile_tih; then
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task ThreadInHole --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_ThreadInHole.json" \
    > "$out/profile_ThreadInHole.txt" 2>&1
  echo "profile_ThreadInHole rc=$? $(head -4 "$out/profile_ThreadInHole.txt" | tr '\n' ' ' | cut -c1-400)"
fi
echo "all checks done at $(( $(date +%s) - t0 )) s"
run_queue "${JOBS:-$d/next_jobs_beside.txt}" "${QUEUE_DEADLINE:-1100}"
