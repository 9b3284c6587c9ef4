#!/usr/bin/env bash
# One GPU lease: cartpole-balance at the paper's model sizes. The teacher learns on states
# while writing D, the student is distilled from D for STUDENT_STEPS updates (10K), and
# teacher, student and the zero-action floor are evaluated on held-out scenes. Every output
# and the seconds each stage took (timings.json) go to OUT. Every stage resumes where it
# stopped: run the same command again on the next lease.
#
#   bash scripts/gpu.sh [OUT]        # OUT defaults to runs/gpu
#
# Settings (environment): DEVICE (cuda), PRESET (paper), FRAMES (D's frames, 120000),
# LEARN_FRAMES (frames the teacher learns for, 100000), LEARN_UNTIL_RETURN (990: learning
# stops at the first evaluation of it, as in the quick preset; "null": never), STUDENT_STEPS
# (10000), RECIPE (dense), EVAL_EPISODES (10), TASK (cartpole-balance), COMPILE (on: both
# stages' updates compiled, with CUDA graphs, on a CUDA device; off at tiny size, where
# compiling takes minutes for updates that take seconds), and COLLECT_SET and DISTIL_SET:
# space-separated KEY=VALUE settings passed on as --set (e.g. DISTIL_SET=frame_steps=20000).
# PRESET=tiny DEVICE=cpu runs it at test sizes in seconds (the preset's own frames;
# tests/test_gpu_script.py does).
#
# On a machine that cannot reach a package index but has a CUDA torch, first install the
# wheels that scripts/offline_bundle.py gathered elsewhere (scripts/offline_install.sh).
#
# The frame budget is a plan for a 25-minute lease: each stage's rate, measured at paper sizes
# on an H200, adds up to ~19 minutes there plus the dense recipe's single-frame stage
# (docs/performance.md), but the whole has not run on a GPU: the first run's timings.json is
# the measurement.
set -euo pipefail
if command -v twist-collect >/dev/null 2>&1; then
  # Already installed (an active environment, or a GPU image with the package on PATH):
  # no virtual environment, whose pinned CPU torch would replace the image's CUDA build.
  export MUJOCO_GL="${MUJOCO_GL:-egl}"
  cd "$(dirname "$0")/.."
else
  . "$(dirname "$0")/bootstrap.sh"
fi
OUT="${1:-runs/gpu}"
TASK="${TASK:-cartpole-balance}"
PRESET="${PRESET:-paper}"
DEVICE="${DEVICE:-cuda}"
mkdir -p "$OUT"
COLLECT_SETTINGS=()
if [[ "$PRESET" != tiny ]]; then
  COLLECT_SETTINGS=(--frames "${FRAMES:-120000}" --set "learn_frames=${LEARN_FRAMES:-100000}"
          --set freeze_best=true --set "learn_until_return=${LEARN_UNTIL_RETURN:-990}")
fi
STEPS=()
if [[ -n "${STUDENT_STEPS:-}" || "$PRESET" != tiny ]]; then STEPS=(--steps "${STUDENT_STEPS:-10000}"); fi
# On a GPU both stages' updates run compiled with CUDA graphs: on an H200 the teacher's update
# took 22.8 ms compiled against 195 eager, and the dense recipe's whole window objective ran
# 49 updates/s, after ~3 and ~4 minutes of compiling (docs/performance.md).
COMPILE="${COMPILE:-$([[ "$PRESET" == tiny ]] && echo off || echo on)}"
DISTIL_SETTINGS=()
if [[ "$DEVICE" == cuda* ]]; then
  COLLECT_SETTINGS+=(--set "compile=$COMPILE")
  DISTIL_SETTINGS=(--set "compute.compile=$([[ "$COMPILE" == on ]] && echo true || echo false)")
fi
# The caller's settings come last, so they override the script's.
for setting in ${COLLECT_SET:-}; do COLLECT_SETTINGS+=(--set "$setting"); done
for setting in ${DISTIL_SET:-}; do DISTIL_SETTINGS+=(--set "$setting"); done
EVAL=(--episodes "${EVAL_EPISODES:-10}")
if [[ "$PRESET" == tiny ]]; then EVAL=(--episodes 2 --max-steps 20); fi

. scripts/stages.sh  # both branches above leave the working folder at the repository's root

RESUME=()
if [[ -d "$OUT/dataset/collect" ]]; then RESUME=(--resume); fi
stage collect twist-collect --task "$TASK" --preset "$PRESET" --device "$DEVICE" \
      --out "$OUT/dataset" --quiet "${COLLECT_SETTINGS[@]}" "${RESUME[@]}"
RESUME=()
if [[ -f "$OUT/student/config.json" ]]; then RESUME=(--resume); fi
stage distil twist-distil --dataset "$OUT/dataset" --out "$OUT/student" --preset "$PRESET" \
      --recipe "${RECIPE:-dense}" --device "$DEVICE" --quiet "${STEPS[@]}" \
      "${DISTIL_SETTINGS[@]}" "${RESUME[@]}"
RESUME=()
if [[ -f "$OUT/eval/episodes.csv" ]]; then RESUME=(--resume); fi
stage eval twist-eval --agent "oracle=$OUT/dataset/collect/collect-000/teacher.pt" \
      --agent "student=$OUT/student/agent.pt" --agent zero --dr heldout --device "$DEVICE" \
      --batch 10 --quiet --out "$OUT/eval" "${EVAL[@]}" "${RESUME[@]}"
write_timings "$OUT/timings.json" "preset=$PRESET" "device=$DEVICE"
cat "$OUT/timings.json"
echo "lease run done: results in $OUT"
