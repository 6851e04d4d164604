#!/usr/bin/env bash
# The README's main job on the built-in `small-mixed` synthetic sequence:
# simulate -> ground truth -> extract -> evaluate protocols 1 and 2 -> plot.
# Everything goes to results/quickstart/ (replaced on every run of this script).
set -euo pipefail
cd "$(dirname "$0")/.."
out=results/quickstart
descriptors=lidar-iris,scan-context,m2dp,esf

if [ -e "$out" ]; then
  echo "== replacing the previous quick-start output in $out"
fi
mkdir -p "$out"

echo "== 1/5 simulate the built-in sequence small-mixed (400 HDL-64 scans, known loops)"
liris simulate "$out/sequence" --world small-mixed --overwrite

echo "== 2/5 ground truth from the poses alone"
liris gt "$out/sequence"

echo "== 3/5 extract and cache the four descriptors"
liris extract "$out/sequence" --descriptor "$descriptors" --cache-dir "$out/cache"

echo "== 4/5 evaluate protocol 1 (best match, E=30) and protocol 2 (all pairs)"
liris eval "$out/sequence" --protocol 1 --protocol 2 --descriptor "$descriptors" \
  --cache-dir "$out/cache" --out "$out/run" --overwrite

echo "== 5/5 figures"
liris plot "$out/run"
echo "== done: metrics in $out/run/metrics.json, figures in $out/run/figures/"
