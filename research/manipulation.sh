#!/usr/bin/env bash
# Every command of the results' manipulation section for one task, in order, resumable: a step
# whose output is complete is skipped, an interrupted one is resumed (the commands' --resume).
#
#   bash research/manipulation.sh panda-lift runs/plift [SEED]
#
# Environment (the defaults are the documented commands'):
#   FRAMES, LEARN     collection frames and learning frames (450000, 400000); raising them on a
#                     later call extends an unfrozen collection
#   PRESET, COMPILE   model sizes and schedule (quick), the compiled update (on)
#   DISTIL_SET        extra read-out settings, e.g. "readout_stage.min_pairing=0.45" for push
#   DREAMER_STEPS     Dreamer w/ DR's updates (800, as the DMC rows)
#   EPISODES          held-out episodes per preset (50)
#   STOP_AFTER        collect | verify | student | eval-student | dreamer: stop after that step
set -euo pipefail
TASK=${1:?usage: manipulation.sh TASK OUT [SEED]}
OUT=${2:?usage: manipulation.sh TASK OUT [SEED]}
SEED=${3:-0}
PRESET=${PRESET:-quick}
D=$OUT/dataset
TEACHER=$D/collect/collect-000/teacher.pt
mkdir -p "$OUT"
log() { echo "$(date -u +%H:%M:%S) $*"; }
stop_after() { if [ "${STOP_AFTER:-}" = "$1" ]; then log "stopped after $1"; exit 0; fi; }

if [ ! -f "$OUT/collect.done" ]; then
  log "collect $TASK seed $SEED"
  twist-collect --task "$TASK" --preset "$PRESET" --out "$D" --frames "${FRAMES:-450000}" \
    --seed "$SEED" --dr train-wide-full --set learn_frames="${LEARN:-400000}" --set compile="${COMPILE:-on}" \
    --quiet --resume
  touch "$OUT/collect.done"
fi
stop_after collect

if [ ! -f "$OUT/verify.done" ]; then
  log "verify"
  twist-data verify "$D" --rerender 20 | tee "$OUT/verify.txt"
  touch "$OUT/verify.done"
fi
stop_after verify

distil_set=(--set readout_stage.units=teacher)
for kv in ${DISTIL_SET:-}; do distil_set+=(--set "$kv"); done
if [ ! -f "$OUT/student.done" ]; then
  log "student (readout recipe)"
  twist-distil --dataset "$D" --out "$OUT/ro" --preset "$PRESET" --recipe readout \
    --teacher "$TEACHER" "${distil_set[@]}" --quiet --resume
  touch "$OUT/student.done"
fi
stop_after student

agents=(--agent "teacher=$TEACHER" --agent "student=$OUT/ro/agent.pt")
if [ ! -f "$OUT/eval-student.done" ]; then
  log "evaluate the student"
  twist-eval --task "$TASK" "${agents[@]}" --agent zero --dr heldout,heldout-full \
    --episodes "${EPISODES:-50}" --batch 10 --out "$OUT/eval-student" | tee "$OUT/eval-student.txt"
  touch "$OUT/eval-student.done"
fi
stop_after eval-student

if [ ! -f "$OUT/dreamer.done" ]; then
  log "Dreamer w/ DR"
  twist-baseline --dataset "$D" --kind dreamer --steps "${DREAMER_STEPS:-800}" --preset "$PRESET" \
    --out "$OUT/dreamer" --quiet --resume
  touch "$OUT/dreamer.done"
fi
stop_after dreamer

if [ ! -f "$OUT/eval.done" ]; then
  log "evaluate every agent under each deployment factor"
  twist-eval --task "$TASK" "${agents[@]}" --agent "dreamer=$OUT/dreamer/agent.pt" --agent zero \
    --dr heldout,heldout-camera,heldout-light,heldout-physics,heldout-full \
    --episodes "${EPISODES:-50}" --batch 10 --out "$OUT/eval" | tee "$OUT/eval.txt"
  touch "$OUT/eval.done"
fi
log "done: $OUT/eval.txt"
