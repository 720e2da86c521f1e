#!/usr/bin/env bash
# A short single-GPU lease of the thirty-fourth session: ThreadInHole's per-vertex tet solve with its rotations
# refreshed once per sweep (World.tet_rotation_update "sweep", kernels/vbd.py refresh_tet_rotations; the task's new
# default) and its layout without the pinned vertices, colours packed for 32 lanes (8 passes per sweep instead of 9),
# against the code before (70ff287, /tmp/old with its own benchmark script) and against the per-vertex rotations on the
# new layout, same call; ThreadInHole's expert on the new default (256 first episodes); RopeThreading and RopeCutting
# against 70ff287 (their particle contact launch now leaves out the mesh SDF query: sm_90 108 -> 66 registers); the
# GPU tests of the register chain solve's changed env test, the colour packing, the fused tets and the contact
# variants; last the per-vertex rotations on the new layout.
# Everything under $OUT/q34, packed into $OUT/q34.tgz at the end (a call returns at most 8 files).
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
out=$OUT/q34
mkdir -p "$out"
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME TASK PYTHONPATH SCRIPT [bench_env.py options...]
  local name=$1 task=$2 path=$3 script=$4
  shift 4
  [ "$(left)" -gt 30 ] || { echo "$name skipped (time)"; return; }
  PYTHONPATH=$path timeout $(( $(left) - 10 )) python3 "$script" --task "$task" --device "$dev" --num-envs 4096 \
    --seconds 3 --policy expert --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
old=/tmp/site:/tmp/old
b tih_new ThreadInHole "$new" benchmarks/bench_env.py
b tih_old ThreadInHole "$old" /tmp/old/benchmarks/bench_env.py
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 benchmarks/expert_success.py --task ThreadInHole --device "$dev" \
    --num-envs 256 --action-types CONTINUOUS --out "$out/expert_tih.jsonl" > "$out/expert_tih.txt" 2>&1
  echo "expert rc=$? $(tail -1 "$out/expert_tih.txt" | cut -c1-260)"
fi
b rt_new RopeThreading "$new" benchmarks/bench_env.py
b rt_old RopeThreading "$old" /tmp/old/benchmarks/bench_env.py
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_colour_packing.py \
    tests/test_fused_tets.py tests/test_contact.py -k "packing or vertex_layout or fused_tet or rejected or without_meshes" \
    --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
b rc_new RopeCutting "$new" benchmarks/bench_env.py
b rc_old RopeCutting "$old" /tmp/old/benchmarks/bench_env.py
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_chains_registers.py \
    -k env_config --device "$dev" > "$out/pytest_registers_cuda.txt" 2>&1
  echo "pytest registers rc=$? $(tail -1 "$out/pytest_registers_cuda.txt")"
fi
b tih_vertex ThreadInHole "$new" benchmarks/bench_env.py --set hole_rotation_update='"vertex"'
echo "done in $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q34.tgz" -C "$OUT" q34 && rm -rf "$out"
