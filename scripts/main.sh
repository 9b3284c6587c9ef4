#!/usr/bin/env bash
# The main job on the embedded default task, cartpole-balance. Today: record random-policy
# episodes with K=2 domain-randomised views, inspect, verify (including a pixel-exact
# re-render), re-render under held-out DR, export, and draw a contact sheet.
# (Teacher collection, distillation and evaluation join as they land.)
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
OUT="${1:-runs/demo}"
TASK="${TASK:-cartpole-balance}"
rm -rf "$OUT/dataset" "$OUT/heldout"
twist-data record "$TASK" "$OUT/dataset" --episodes 4 --dr train --views 2 --image-size 64
twist-data info "$OUT/dataset"
twist-data episodes "$OUT/dataset" --csv "$OUT/episodes.csv"
twist-data verify "$OUT/dataset" --rerender 20
twist-data render "$OUT/dataset" "$OUT/heldout" --dr heldout --views 2
twist-data export-video "$OUT/dataset" "$OUT/episode0.mp4" --episode 0
twist-data export-video "$OUT/heldout" "$OUT/episode0-heldout.mp4" --episode 0
twist-data export-hdf5 "$OUT/dataset" "$OUT/dataset.h5"
twist-data contact-sheet "$TASK" "$OUT/contact-sheet.png"
echo "main job done: results in $OUT"
