#!/usr/bin/env bash
# Re-split the Warp wheel that ../shared/tools/device-wheels.sh fetched into parts that each fit one `device run` call
# beside the checkout (the tool carries the tracked tree with every call and refuses more than 64 MiB in all; in the
# twenty-sixth session the tree had grown to 19.2 MiB and the 45 MiB parts were refused):
#   bash train/device/split_wheel.sh
# Writes .device/w1 .. .device/wN (the last one also holds warp_name) and .device/wheels (the small wheels alone),
# and prints N and the part size. The part size leaves 8 MiB beside the tracked tree for what a call adds.
set -euo pipefail
root=$(git rev-parse --show-toplevel)
cd "$root/.device"
name=$(cat warp_name 2>/dev/null || cat p3/warp_name)
whl=/tmp/lapwarp_wheel/$name
mkdir -p /tmp/lapwarp_wheel
if [ ! -f "$whl" ]; then
  cat p1/warp_part_* p2/warp_part_* p3/warp_part_* > "$whl"
fi
python3 -c "import sys, zipfile; zipfile.ZipFile(sys.argv[1]).testzip() is None or sys.exit('corrupt wheel')" "$whl"
# the sum of the tracked files' sizes (du -c through xargs totals each of xargs' batches apart: in the thirty-eighth
# session the last batch's 3.7 MB stood for a 28.5 MiB tree, and every part was refused)
tree=$(cd "$root" && git ls-files -z | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}')
part=$(( (64 - 8) * 1048576 - tree ))
[ "$part" -ge $((8 * 1048576)) ] || { echo "the tracked tree ($tree bytes) leaves no room for wheel parts"; exit 1; }
rm -rf w[0-9]* wheels /tmp/lapwarp_wheel/part_*
(cd /tmp/lapwarp_wheel && split -b "$part" "$name" part_)
n=0
for p in /tmp/lapwarp_wheel/part_*; do n=$((n + 1)); mkdir -p "w$n"; mv "$p" "w$n/"; done
echo "$name" > "w$n/warp_name"
mkdir -p wheels && cp small/*.whl wheels/
echo "$n parts of at most $part bytes (tracked tree $tree bytes): .device/w1 .. .device/w$n;" \
  "small wheels in .device/wheels"
