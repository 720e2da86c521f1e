#!/usr/bin/env bash
# A short single-GPU lease of the thirty-fourth session: ThreadInHole's per-vertex tet solve with its rotations
# refreshed once per sweep (World.tet_rotation_update "sweep", kernels/vbd.py refresh_tet_rotations; the task's new
# default) and its layout without the pinned vertices, colours packed for 32 lanes (8 passes per sweep instead of 9),
# against the code before (70ff287, /tmp/old with its own benchmark script) and against the per-vertex rotations on the
# new layout, same call; then the GPU tests of the register chain solve's changed env test, the colour packing and the
# fused tets, and ThreadInHole's expert on the new default (256 first episodes).
# Everything under $OUT/q34, packed into $OUT/q34.tgz at the end (a call returns at most 8 files).
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
out=$OUT/q34
mkdir -p "$out"
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME PYTHONPATH SCRIPT [bench_env.py options...]
  local name=$1 path=$2 script=$3
  shift 3
  [ "$(left)" -gt 30 ] || { echo "$name skipped (time)"; return; }
  PYTHONPATH=$path timeout $(( $(left) - 10 )) python3 "$script" --task ThreadInHole --device "$dev" --num-envs 4096 \
    --seconds 3 --policy expert --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
b tih_new "$new" benchmarks/bench_env.py
b tih_old /tmp/site:/tmp/old /tmp/old/benchmarks/bench_env.py
b tih_vertex "$new" benchmarks/bench_env.py --set hole_rotation_update='"vertex"'
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py \
    tests/test_colour_packing.py tests/test_fused_tets.py --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
  echo "expert rc=$? $(tail -1 "$out/expert_tih.txt" | cut -c1-260)"
fi
echo "done in $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q34.tgz" -C "$OUT" q34 && rm -rf "$out"
