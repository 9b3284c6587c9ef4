#!/usr/bin/env bash
# The main job on the embedded default. Today: write a synthetic matching dataset, inspect,
# verify and export it. (Collection, distillation and evaluation join as they land.)
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
OUT="${1:-runs/demo}"
rm -rf "$OUT/dataset"
twist-data synth "$OUT/dataset" --episodes 8 --steps 251 --views 2 --image-size 64 --shards 2
twist-data info "$OUT/dataset"
twist-data episodes "$OUT/dataset" --csv "$OUT/episodes.csv"
twist-data verify "$OUT/dataset"
twist-data export-video "$OUT/dataset" "$OUT/episode0.mp4" --episode 0
twist-data export-hdf5 "$OUT/dataset" "$OUT/dataset.h5"
echo "main job done: results in $OUT"
