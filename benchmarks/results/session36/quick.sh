#!/usr/bin/env bash
# A short single-GPU lease of the thirty-sixth session, same call throughout: the tet rotation extraction without
# trigonometry (kernels/xpbd.py extract_rotation: each turn as the quaternion (omega / 2, 1); sm_90: the 32 B stack
# frame of every extracting kernel gone) with the register caps the session made task defaults, against the code
# before both (555e7ee, carried as .device/small/old): LigatingLoop (its cavity's fused XPBD sweep extracts in every
# projection: 48.7 % of its kernel time), ThreadInHole (its refresh kernel: 10.2 %), TissueDissection (refresh), then
# LigatingLoop's new code with its rods uncapped (the extraction alone), the GPU tests of the extraction and the
# fused tets, and RopeThreading / RopeCutting on the new defaults.
# Everything under $OUT/q36, packed into $OUT/q36.tgz at the end (a call returns at most 8 files).
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
out=$OUT/q36
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:$PWD/.device/small/old
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME TASK PYTHONPATH [bench_env.py options...]
  local name=$1 task=$2 path=$3
  shift 3
  [ "$(left)" -gt 30 ] || { echo "$name skipped (time)"; return; }
  PYTHONPATH=$path timeout $(( $(left) - 10 )) python3 benchmarks/bench_env.py --task "$task" --device "$dev" \
    --num-envs 4096 --seconds 3 --policy expert --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
b ll_old LigatingLoop "$old"
b ll_new LigatingLoop "$new"
b tih_old ThreadInHole "$old"
b tih_new ThreadInHole "$new"
b td_old TissueDissection "$old"
b td_new TissueDissection "$new"
b ll_new_rods255 LigatingLoop "$new" --max-registers solve_rods_fused=255
if [ "$(left)" -gt 50 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_fused_tets.py \
    tests/test_physics_deformables.py -k "tet or extracted" --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
b rt_new RopeThreading "$new"
b rc_new RopeCutting "$new"
echo "done in $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q36.tgz" -C "$OUT" q36 && rm -rf "$out"
