#!/usr/bin/env bash
# A short single-GPU lease of the thirty-fifth session: the XPBD tet sweep with its rotations refreshed once per sweep
# (World.tet_rotation_update "sweep" for XPBD, kernels/xpbd.py refresh_tet_rotations + project_tet_lagged: the fused
# sweep without the extraction, sm_90 114 registers without a frame against 128 + 32 B), TissueDissection's new default
# (tissue_rotation_update "sweep"), against the code before (8e8c612, /tmp/old with its own benchmark script) and against
# the per-tet extraction on the new code, same call; STATE and RGB 64x64; its expert on the new default (256 first
# episodes, R = 2 and 4, continuous); the GPU tests of the fused tets (the lagged XPBD cases); LigatingLoop's cavity with
# the lagged rotations (not its default: the cavity is stiffer and the loop does not close to 0.8) against its default;
# caps of the lagged fused kernel (96: a 16 B frame; 64: 152 B); a TissueDissection soak on the new default.
# Everything under $OUT/q35, packed into $OUT/q35.tgz at the end (a call returns at most 8 files).
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
out=$OUT/q35
mkdir -p "$out"
new=/tmp/site:$PWD
old=/tmp/site:/tmp/old
left() { echo $(( limit - ($(date +%s) - t0) )); }
b() {  # NAME TASK PYTHONPATH SCRIPT [bench_env.py options...]
  local name=$1 task=$2 path=$3 script=$4
  shift 4
  [ "$(left)" -gt 30 ] || { echo "$name skipped (time)"; return; }
  PYTHONPATH=$path timeout $(( $(left) - 10 )) python3 "$script" --task "$task" --device "$dev" --num-envs 4096 \
    --seconds 3 --policy expert --out "$out/$name.json" "$@" > "$out/$name.txt" 2>&1
  echo "$name rc=$? $(tail -1 "$out/$name.txt")"
}
b td_new TissueDissection "$new" benchmarks/bench_env.py
b td_old TissueDissection "$old" /tmp/old/benchmarks/bench_env.py
b td_vertex TissueDissection "$new" benchmarks/bench_env.py --set tissue_rotation_update='"vertex"'
b td_rgb_new TissueDissection "$new" benchmarks/bench_env.py --obs RGB
b td_rgb_old TissueDissection "$old" /tmp/old/benchmarks/bench_env.py --obs RGB
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 benchmarks/expert_success.py --task TissueDissection \
    --device "$dev" --num-envs 256 --action-types CONTINUOUS --config rows_to_cut=2 --config rows_to_cut=4 \
    --out "$out/expert_td.jsonl" > "$out/expert_td.txt" 2>&1
  echo "expert rc=$? $(tail -2 "$out/expert_td.txt" | tr '\n' ' ' | cut -c1-300)"
fi
if [ "$(left)" -gt 40 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 -m pytest -q -p no:cacheprovider tests/test_fused_tets.py \
    --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
fi
b ll_sweep LigatingLoop "$new" benchmarks/bench_env.py --set cavity_rotation_update='"sweep"'
b ll_new LigatingLoop "$new" benchmarks/bench_env.py
b td_cap96 TissueDissection "$new" benchmarks/bench_env.py --max-registers solve_tets_fused=96
b td_cap64 TissueDissection "$new" benchmarks/bench_env.py --max-registers solve_tets_fused=64
if [ "$(left)" -gt 60 ]; then
  PYTHONPATH=$new timeout $(( $(left) - 10 )) python3 benchmarks/soak.py --device "$dev" --num-envs 4096 \
    --env-steps 3e6 --tasks TissueDissection --action-types CONTINUOUS --out "$out/soak_td.jsonl" > "$out/soak_td.txt" 2>&1
  echo "soak rc=$? $(tail -2 "$out/soak_td.txt" | tr '\n' ' ' | cut -c1-300)"
fi
echo "done in $(( $(date +%s) - t0 )) s"
tar czf "$OUT/q35.tgz" -C "$OUT" q35 && rm -rf "$out"
