#!/usr/bin/env bash
# The forty-sixth session's quick call (one H200, after the lease), in order of need, each item skipped once DEADLINE
# (s, default 430) has passed; lines to stdout as they finish, files under $OUT/q46 packed into $OUT/q46.tgz:
# 1. RGB 64x64 steps (expert, 4,096 envs) of ThreadInHole and RopeThreading on HEAD (the rasteriser's and shader's
#    kernels at 48 registers since the lease) against p5: the shading pass with an observation frame writing neither
#    the bytes nor the depth outputs (the env reads only the frame there: 7 of ~39 bytes per pixel);
# 2. PrecisionCutting (expert) on HEAD against p6 / p7: its cloth's open walk with launch bounds (256, 3) / (256, 4)
#    and register spills in shared memory (sm_90: 80 registers + 48 B local + 72 B shared / 64 + 112 + 72, against
#    96 registers and a 64 B local frame), alternated;
# 3. the six #17 / #18 tasks' steps on HEAD (the lease's deadline skipped them);
# 4. GPU tests of the renderer, the kernel resources and LigatingLoop.
# Probes' patches: results/session46/probes.
set -u
. train/device/beside_lib.sh
DEADLINE=${DEADLINE:-430} beside_init "$OUT/q46"
export PYTHONUNBUFFERED=1
p5=/tmp/site:$PWD/.device/small/p5
p6=/tmp/site:$PWD/.device/small/p6
p7=/tmp/site:$PWD/.device/small/p7
pack() { tar czf "$OUT/q46.tgz" -C "$OUT" q46; }
in_time rgb && {
  bench rgb_tih ThreadInHole expert --obs RGB
  bench_on "$p5" rgb_tih_p5 ThreadInHole expert --obs RGB
  bench rgb_rt RopeThreading expert --obs RGB
  bench_on "$p5" rgb_rt_p5 RopeThreading expert --obs RGB
  pack
}
in_time pc && {
  bench pc_a PrecisionCutting expert
  bench_on "$p6" pc_p6_a PrecisionCutting expert
  bench_on "$p7" pc_p7_a PrecisionCutting expert
  pack
}
for task in TissueDissection RopeCutting ThreadInHole RopeThreading LigatingLoop; do
  in_time "step_$task" && bench "step_$task" "$task" expert
done
pack
in_time pc_b && {
  bench pc_b PrecisionCutting expert
  bench_on "$p6" pc_p6_b PrecisionCutting expert
  bench_on "$p7" pc_p7_b PrecisionCutting expert
  pack
}
if in_time pytest; then
  PYTHONPATH=$new timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_render.py tests/test_kernel_resources.py \
    --device "$dev" > "$out/pytest_cuda.txt" 2>&1
  echo "pytest rc=$? $(tail -1 "$out/pytest_cuda.txt")"
  pack
fi
echo "done in $(( $(date +%s) - t0 )) s"
