#!/usr/bin/env bash
# The forty-third session's second quick call (one H200, LIMIT seconds, default 300): the fused rod launch's lanes per
# env (world.rod_block_threads, 32) on RopeThreading at 64 (199.9k against 194.5k at 32 in the first call) and 128,
# alternated with 32; RopeCutting at 64 lanes with the prediction in the rod launch on and off (on at 32 lanes was
# 2.9 % slower); RopeThreading's RGB 64x64 step at 32 and 64 lanes; its experts at 64 lanes.
set -u
t0=$(date +%s)
limit=${LIMIT:-300}
dev=${DEVICE:-cuda:0}
n=4096
out=$OUT/q43b
mkdir -p "$out"
export PYTHONUNBUFFERED=1
new=/tmp/site:$PWD
left() { echo $(( limit - ($(date +%s) - t0) )); }
pack() { tar czf "$OUT/q43b.tgz" -C "$OUT" q43b; }
. train/device/beside_lib.sh  # bench
bench rt64_a RopeThreading expert --rod-block-threads 64
bench rt32_a RopeThreading expert
bench rt128 RopeThreading expert --rod-block-threads 128
bench rt64_b RopeThreading expert --rod-block-threads 64
pack
bench rc64 RopeCutting expert --rod-block-threads 64
bench rc64_nopred RopeCutting expert --rod-block-threads 64 --predict-in-rod-sweep off
bench rc32_nopred RopeCutting expert --predict-in-rod-sweep off
pack
[ "$(left)" -gt 60 ] && bench rgb_rt64 RopeThreading expert --obs RGB --rod-block-threads 64
pack
echo "done in $(( $(date +%s) - t0 )) s"
