#!/usr/bin/env bash
# The README's main job on a built-in synthetic sequence: simulate, extract, evaluate, plot.
set -euo pipefail
cd "$(dirname "$0")/.."
out=results/quickstart
mkdir -p "$out"
echo "== ground truth on the real KITTI 00 poses (if ../shared is present)"
if [ -f ../shared/data/kitti/poses/00.txt ]; then
  liris gt --poses ../shared/data/kitti/poses/00.txt --exclude reference
fi
