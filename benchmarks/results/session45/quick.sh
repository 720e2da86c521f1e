#!/usr/bin/env bash
# The forty-fifth session's quick call (one H200), same call, in order of need (LIMIT seconds, default 420):
# 1. ThreadInHole (expert, 4,096 envs, STATE): the old tree (.device/small/old = 8b4ec6a's lapwarp) against HEAD (its
#    hole's per-vertex sweep with stored rotations forming each incidence's terms from F m, a triple and a cross
#    product with rest-shape factors built once, and multiplying by the tets' stiffnesses instead of dividing by
#    their compliances: sm_90 at its 64-register cap without the 80-byte spill frame; and its thread on the split
#    register solve at 3e-4 m, 212.9k against 207.6k in the lease) and a probe (.device/small/varB:
#    HEAD with the deformation-gradient form of the terms, multiplying by the stiffnesses; a 32-byte spill frame as the
#    old tree's: is a gain the arithmetic or the spill?), alternated, then RGB 64x64 of the old tree and HEAD;
# 2. GPU tests of the per-vertex solve (the lagged terms against the deformation-gradient form, the fused sweep against
#    the per-colour launches, per-env materials, ThreadInHole's sag and push against the closed form);
# 3. ThreadInHole's expert (256 first episodes, continuous and discrete, each configuration) on HEAD;
# 4. its profile on HEAD.
# Lines go to stdout as they finish; files under $OUT/q45, packed into $OUT/q45.tgz after each.
set -u
t0=$(date +%s)
limit=${LIMIT:-420}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q45
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
varb=/tmp/site:$PWD/.device/small/varB
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q45.tgz" -C "$OUT" q45; }
. train/device/beside_lib.sh  # bench, bench_old
timed() { [ "$(left)" -gt 30 ] || { echo "skipped $1"; return 1; }; }
timed tih_new_a && bench tih_new_a ThreadInHole expert
timed tih_old_a && bench_old tih_old_a ThreadInHole expert
timed tih_varb_a && bench_on "$varb" tih_varb_a ThreadInHole expert
timed tih_new_b && bench tih_new_b ThreadInHole expert
timed tih_old_b && bench_old tih_old_b ThreadInHole expert
timed tih_varb_b && bench_on "$varb" tih_varb_b ThreadInHole expert
pack
timed rgb_tih_new && bench rgb_tih_new ThreadInHole expert --obs RGB
timed rgb_tih_old && bench_old rgb_tih_old ThreadInHole expert --obs RGB
pack
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 40 )) python3 -m pytest -q -p no:cacheprovider tests/test_vbd_lagged_terms.py \
    tests/test_fused_tets.py tests/test_solver.py tests/test_thread_in_hole.py tests/test_chains_registers.py \
    -k "lagged or fused or per_env or vertex or sag or push or tunnel or wall or keeps_the_converged" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt") at $(( $(date +%s) - t0 )) s"
  pack
fi
if [ "$(left)" -gt 45 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS DISCRETE --config configuration=normal --config configuration=flexible \
    --config configuration=inverted --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
  echo "expert_tih rc=$? $(grep -o '"success_rate": [0-9.]*' "$out/expert_tih.jsonl" | tr '\n' ' ') at $(( $(date +%s) - t0 )) s"
  pack
fi
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 5 )) python3 benchmarks/profile_step.py --task ThreadInHole --device "$dev" \
    --num-envs "$n" --steps 5 --warmup 20 --top 30 --out "$out/profile_ThreadInHole.json" \
    > "$out/profile_ThreadInHole.txt" 2>&1
  echo "profile_ThreadInHole rc=$? $(head -3 "$out/profile_ThreadInHole.txt" | tr '\n' ' ' | cut -c1-300)"
  pack
fi
echo "done in $(( $(date +%s) - t0 )) s"
rm -rf "$out"
