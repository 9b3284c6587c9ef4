#!/usr/bin/env bash
# The main job on the embedded default task, cartpole-balance: train the state teacher with
# the `quick` preset while writing the matching dataset D (K=2 domain-randomised views per
# step), then inspect, verify (including a pixel-exact re-render), re-render the last episode
# under held-out DR for its video, export, and draw a contact sheet; then distil the vision
# student from D offline and evaluate teacher (on states), student (on images) and the
# zero-action floor on held-out backgrounds.
# PRESET=tiny gives a smoke run of seconds; SEED=1 (or 2) collects with another seed;
# EVAL_EPISODES sets the held-out episodes (10); DR=train-wide-full renders D with a moved
# camera and changed light (and trains the teacher under the physics factors); DEVICE=cuda trains and acts on a GPU (a CUDA
# torch must then be installed, e.g. an active environment: scripts/gpu.sh shows how). Running
# it again resumes an interrupted run.
# OUT/timings.json gets each stage's seconds and, to compare machines, the seconds of one eager
# teacher update of the preset timed at the start (benchmarks/teacher_update_modes.py).
set -euo pipefail
. "$(dirname "$0")/stages.sh"
if [[ "${DEVICE:-cpu}" != cpu ]] && command -v twist-collect >/dev/null 2>&1; then
  # A GPU machine with twist installed beside its CUDA torch: no virtual environment, whose
  # pinned CPU torch would replace it.
  export MUJOCO_GL="${MUJOCO_GL:-egl}"
  cd "$(dirname "$0")/.."
else
  stage setup . "$(dirname "$0")/bootstrap.sh"  # leaves the working folder at the repository's root
fi
OUT="${1:-runs/demo}"
TASK="${TASK:-cartpole-balance}"
PRESET="${PRESET:-quick}"
SEED="${SEED:-0}"
DR="${DR:-train-wide}"
DEVICE="${DEVICE:-cpu}"
mkdir -p "$OUT"
stage machine_speed python benchmarks/teacher_update_modes.py --preset "$PRESET" --task "$TASK" \
      --variants eager --rounds 5 > "$OUT/machine-speed.json"
RESUME=()
if [[ -d "$OUT/dataset/collect" ]]; then RESUME=(--resume); fi
stage collect twist-collect --task "$TASK" --preset "$PRESET" --seed "$SEED" --dr "$DR" \
      --device "$DEVICE" --out "$OUT/dataset" "${RESUME[@]}"
check_dataset() {  # what twist-data does with D: inspect, verify, re-render, export, draw
  # A resumed job writes these again from the grown D (exports refuse to replace a file
  # unless told to).
  rm -rf "$OUT/heldout"
  twist-data info "$OUT/dataset"
  twist-data episodes "$OUT/dataset" --csv "$OUT/episodes.csv" --overwrite
  twist-data verify "$OUT/dataset" --rerender 20
  twist-data render "$OUT/dataset" "$OUT/heldout" --dr heldout --views 2 --episodes -1
  twist-data export-video "$OUT/dataset" "$OUT/episode-last.mp4" --episode -1 --overwrite
  twist-data export-video "$OUT/heldout" "$OUT/episode-last-heldout.mp4" --episode -1 --overwrite
  twist-data export-hdf5 "$OUT/dataset" "$OUT/dataset.h5" --overwrite
  twist-data contact-sheet "$TASK" "$OUT/contact-sheet.png"
  cp "$OUT/dataset/collect/collect-000/learning-curve.png" "$OUT/learning-curve.png"
}
stage check_dataset check_dataset
DISTIL=()
if [[ -f "$OUT/student/config.json" ]]; then DISTIL=(--resume); fi
# The readout recipe (the student reads D's state into the teacher's own filter; not in the
# paper): RECIPE=paper runs the paper's objective alone, RECIPE=dense the per-frame targets
# beside it (README, "Recipes").
stage distil twist-distil --dataset "$OUT/dataset" --out "$OUT/student" --preset "$PRESET" \
      --recipe "${RECIPE:-readout}" --device "$DEVICE" "${DISTIL[@]}"
cp "$OUT/student/latent-agreement.png" "$OUT/latent-agreement.png"
EVAL=(--episodes "${EVAL_EPISODES:-10}")
if [[ "$PRESET" == tiny ]]; then EVAL=(--episodes 2 --max-steps 50); fi
if [[ -f "$OUT/eval/episodes.csv" ]]; then EVAL+=(--resume); fi
stage eval twist-eval --agent "oracle=$OUT/dataset/collect/collect-000/teacher.pt" \
      --agent "student=$OUT/student/agent.pt" --agent zero --dr heldout \
      --device "$DEVICE" --out "$OUT/eval" "${EVAL[@]}"
write_timings "$OUT/timings.json" "task=$TASK" "preset=$PRESET" "seed=$SEED" "device=$DEVICE" \
  "eager_teacher_update_s=$(python -c 'import json, sys; print(json.load(sys.stdin)["eager_s"])' \
                            < "$OUT/machine-speed.json")"
cat "$OUT/timings.json"
echo "main job done: results in $OUT"
