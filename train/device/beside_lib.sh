#!/usr/bin/env bash
# Helpers for a lease's BESIDE script (train/device/queue.sh runs it from /tmp/queue_code), sourced after it sets
# dev (the device), n (num_envs), out (its result folder), new (its PYTHONPATH) and t0 (its start, seconds), or
# sourced first and followed by `beside_init OUT`, which sets them (and deadline, old) from the environment:
#   beside_init OUT                                      t0 now; dev, n, deadline from DEVICE (cuda:0), NUM_ENVS (4096),
#                                                        DEADLINE (1000); out=OUT (created); new, old the trees' paths
#   in_time NAME                                         whether DEADLINE s since t0 have not passed (else says so)
#   bench NAME TASK POLICY [bench_env.py options...]   one bench_env.py point (STATE, 3 s) into $out/NAME.json / .txt
#   bench_old NAME TASK POLICY [options...]             the same on the old tree (PYTHONPATH=$old, set by the script)
#   bench_variants LABEL TASK POLICY NAME=ARGS...        bench_env.py --variant: each variant's ARGS (options) timed in one
#                                                        process (one start-up and compile) into $out/NAME.json
#   profile TASK [LABEL [options...]]                    benchmarks/profile_step.py (5 steps after 20) into
#                                                        $out/profile_LABEL.* (LABEL: TASK by default)
#   soak TASK ENV_STEPS                                  benchmarks/soak.py (continuous random actions) into $out/soak_TASK.*
#   run_queue JOBS_FILE DEADLINE                         the learning queue on $dev until DEADLINE seconds after t0
beside_init() {  # OUT
  t0=$(date +%s)
  dev=${DEVICE:-cuda:0}
  n=${NUM_ENVS:-4096}
  deadline=${DEADLINE:-1000}
  out=$1
  mkdir -p "$out"
  new=/tmp/site:$PWD
  old=/tmp/site:$PWD/.device/small/old
}

in_time() {  # NAME
  [ $(( $(date +%s) - t0 )) -lt "$deadline" ] || { echo "deadline: skipped $*"; return 1; }
}

bench_on() {  # PYTHONPATH NAME TASK POLICY [options...]
  local path=$1 name=$2 task=$3 policy=$4
  shift 4
  PYTHONPATH=$path python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy "$policy" "$@" --out "$out/$name.json" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}

bench() { bench_on "$new" "$@"; }

bench_variants() {  # LABEL TASK POLICY NAME=ARGS...
  local label=$1 task=$2 policy=$3 variants=()
  shift 3
  for v in "$@"; do variants+=(--variant "$v"); done
  PYTHONPATH=$new python3 benchmarks/bench_env.py --task "$task" --device "$dev" --num-envs "$n" --seconds 3 \
    --obs STATE --policy "$policy" "${variants[@]}" --out "$out/$label.json" > "$out/$label.txt" 2>&1
  echo "$label rc=$?"
  grep "^variant " "$out/$label.txt"
}

profile() {  # TASK [LABEL [profile_step.py options...]]
  local task=$1 label=${2:-$1}
  shift $(( $# < 2 ? $# : 2 ))
  PYTHONPATH=$new timeout 200 python3 benchmarks/profile_step.py --task "$task" --device "$dev" --num-envs "$n" \
    --steps 5 --warmup 20 --top 30 "$@" --out "$out/profile_$label.json" > "$out/profile_$label.txt" 2>&1
  echo "profile_$label rc=$? $(head -4 "$out/profile_$label.txt" | tr '\n' ' ' | cut -c1-400)"
}

soak() {  # TASK ENV_STEPS
  local task=$1 steps=$2
  PYTHONPATH=$new timeout 300 python3 benchmarks/soak.py --device "$dev" --num-envs "$n" --env-steps "$steps" \
    --tasks "$task" --action-types CONTINUOUS --out "$out/soak_$task.jsonl" > "$out/soak_$task.txt" 2>&1
  echo "soak_$task rc=$? $(tail -1 "$out/soak_$task.txt" | cut -c1-300)"
}

bench_old() { bench_on "$old" "$@"; }

run_queue() {
  local jobs=$1 deadline=$2
  grep -qv '^#' "$jobs" || { echo "no jobs in $jobs"; return 0; }
  local left=$((deadline + t0 - $(date +%s)))
  [ "$left" -gt 0 ] || { echo "no time left for the queue"; return 0; }
  PYTHONPATH=$new python3 train/experiments.py --queue "$jobs" --devices "$dev" \
    --fast-pixels --shared-encoder --skip-done --no-plots --deadline "$left" --out /tmp/r/learning \
    --log-dir /tmp/queue_runs_beside
}
