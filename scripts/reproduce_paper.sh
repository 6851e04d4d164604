#!/usr/bin/env bash
# Reproduce the LiDAR Iris paper's KITTI evaluation on your own copy of KITTI odometry.
#
#   bash scripts/reproduce_paper.sh /path/to/dataset [sequences...]   (default: 00 05 08)
#
# For each sequence it runs both protocols for all four descriptors twice:
#   results/paper/<seq>      paper presets, E = 30 (the paper's text)
#   results/reference/<seq>  reference presets, E = 300 (the authors' code; LiDAR Iris
#                            tries both directions, like matchNum 2)
# then overlays the two with `liris plot --compare`. Existing run folders are kept:
# delete them to recompute. Expect a few minutes per sequence on a 2-core laptop.
set -euo pipefail
if [ $# -lt 1 ]; then
  echo "usage: $0 DATASET_ROOT [SEQ ...]   (DATASET_ROOT holds sequences/ and poses/)" >&2
  exit 2
fi
root=$1
shift
sequences=("${@:-00 05 08}")
# shellcheck disable=SC2206
sequences=(${sequences[*]})
descriptors=lidar-iris,scan-context,m2dp,esf

for seq in "${sequences[@]}"; do
  path="$root/sequences/$seq"
  echo "== KITTI $seq: ground truth"
  liris gt "$path" --exclude paper
  liris gt "$path" --exclude reference
  for setting in paper reference; do
    out="results/$setting/$seq"
    if [ -e "$out" ]; then
      echo "== keeping existing $out"
      continue
    fi
    if [ "$setting" = paper ]; then
      liris eval "$path" --protocol 1 --protocol 2 --descriptor "$descriptors" \
        --preset paper --exclude paper --out "$out"
    else
      liris eval "$path" --protocol 1 --protocol 2 \
        --descriptor lidar-iris:reference,scan-context:reference,m2dp:reference,esf:reference \
        --param lidar-iris.match_mode=both --exclude reference --out "$out"
    fi
    liris plot "$out"
  done
  liris plot --compare "results/paper/$seq" "results/reference/$seq" \
    --out "results/compare-$seq"
done
