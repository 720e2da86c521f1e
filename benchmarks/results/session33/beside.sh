#!/usr/bin/env bash
# The GPU beside the next lease's learning queue (queue.sh's BESIDE; x4: GPU 3, x2: GPU 1 with DEVICE=cuda:1), ~23 min
# (in order of need: what the collections' end cuts off comes last):
# 1. the GPU tests of the register chain solve (kernels/chains_registers.py; RopeCutting's GPU default since the
#    thirty-third session, never run by pytest on a GPU), of the contact buffer that keeps its own count (the clamp
#    launch folded into record_contact), of the last velocity update folded into the stability check, and the hybrid;
# 2. the thirty-third session's code against ac9edb4 (/tmp/old, with its own benchmark scripts), same call:
#    TissueDissection STATE / RGB (two launches fewer per world step: #17's RGB 200k was 0.4 % away), RopeCutting (now
#    "registers"), RopeThreading (now "hybrid"), ThreadInHole, LigatingLoop, PrecisionCutting;
# 3. the experts on the new defaults (RopeCutting on "registers", RopeThreading on "hybrid"), 256 first episodes each,
#    and 10^7-step random-action soaks of both;
# 4. TissueDissection RGB replayed, RopeCutting RGB 64x64 (#17: 200k), the register solve on LigatingLoop's 49-link
#    rod (against its "pcr"; bit-identical to the serial walk on the CPU after two env steps) and PrecisionCutting's
#    cloth, the cloth's serial walk under register caps 80 and 128, RopeCutting's kernel profile on "registers",
#    TissueDissection RGB's profile (launches per env step: 402 in the thirty-second session, 30 fewer expected);
# then the learning queue JOBS until DEADLINE seconds after this script started.
# DEVICE (cuda:3), NUM_ENVS (4096), JOBS (next_jobs_gpu3.txt) and DEADLINE (1400) override.
set -u
t0=$(date +%s)
dev=${DEVICE:-cuda:3}
n=${NUM_ENVS:-4096}
d=benchmarks/results/session33
out=/tmp/r/beside33
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
PYTHONPATH=$new python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py tests/test_contact.py \
  tests/test_physics_basic.py tests/test_chains_hybrid.py --device "$dev" > "$out/pytest_cuda.txt" 2>&1
echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
bench() {  # NAME CODE(new|old) TASK OBS [bench_env.py options...]
  local name=$1 code=$2 task=$3 obs=$4 path=$new script=benchmarks/bench_env.py
  shift 4
  if [ "$code" = old ]; then path=$old; script=/tmp/old/benchmarks/bench_env.py; fi
  PYTHONPATH=$path python3 "$script" --task "$task" --device "$dev" --num-envs "$n" --seconds 3 --obs "$obs" "$@" \
    --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
if [ -d /tmp/old/lapwarp ]; then
  for code in old new; do
    bench td_state_$code $code TissueDissection STATE --policy expert
    bench td_rgb_$code $code TissueDissection RGB --policy expert
    bench rc_$code $code RopeCutting STATE --policy expert
    bench rt_$code $code RopeThreading STATE --policy expert
    bench tih_$code $code ThreadInHole STATE --policy expert
    bench ll_$code $code LigatingLoop STATE --policy expert
    bench pc_$code $code PrecisionCutting STATE --policy expert
  done
fi
for task in RopeCutting RopeThreading; do
  PYTHONPATH=$new python3 benchmarks/expert_success.py --task $task --device "$dev" --num-envs 256 \
    --action-types CONTINUOUS --out "$out/expert_$task.jsonl" > "$out/expert_$task.txt" 2>&1
  echo "expert_$task rc=$? $(tail -1 "$out/expert_$task.txt" | cut -c1-260)"
done
PYTHONPATH=$new python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps 1e7 \
  --tasks RopeCutting RopeThreading --action-types CONTINUOUS --out "$out/soak.jsonl" > "$out/soak.txt" 2>&1
echo "soak rc=$? $(tail -2 "$out/soak.txt" | tr '\n' ' ' | cut -c1-300)"
bench td_rgb_replay new TissueDissection RGB --policy replay --replay-steps 200
bench rc_rgb_new new RopeCutting RGB --policy expert
bench ll_registers new LigatingLoop STATE --policy expert --set chain_solver=registers
bench pc_registers new PrecisionCutting STATE --policy expert --set chain_solver=registers
# the cloth's serial walk under other register caps (96 by default, chains.solve_cloth_chains): the thirty-second
# session's rewrite grew its sm_90 spill frame 160 -> 192 B, and the free cloth lost 2.7 % with it
bench pc_cap80 new PrecisionCutting STATE --policy expert --max-registers solve_chains=80
bench pc_cap128 new PrecisionCutting STATE --policy expert --max-registers solve_chains=128
PYTHONPATH=$new python3 benchmarks/profile_step.py --task RopeCutting --device "$dev" --num-envs "$n" --steps 10 \
  --out "$out/profile_rc.json" > "$out/profile_rc.txt" 2>&1
echo "profile_rc rc=$?"; head -8 "$out/profile_rc.txt"
PYTHONPATH=$new python3 benchmarks/profile_step.py --task TissueDissection --device "$dev" --num-envs "$n" --steps 10 \
  --set observation_type=RGB --out "$out/td_rgb_profile.json" > "$out/td_rgb_profile.txt" 2>&1
echo "td_rgb_profile rc=$? $(grep -m1 "kernel time per env step" "$out/td_rgb_profile.txt")"
left=$((${DEADLINE:-1400} + t0 - $(date +%s)))
[ "$left" -gt 0 ] || { echo "no time left for the queue"; exit 0; }
PYTHONPATH=$new python3 train/experiments.py --queue "${JOBS:-$d/next_jobs_gpu3.txt}" --devices "$dev" \
  --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
  --log-dir /tmp/queue_runs_beside
