#!/usr/bin/env bash
# One task of the benchmark end to end, resumable: a step whose output is complete is skipped,
# an interrupted one resumed (the commands' --resume). Run it again after any stop.
#
#   bash research/task.sh walker-walk runs/w4 [SEED]
#
# Steps: collect (teacher on the full state, D) · verify · pairs (D re-rendered with frame
# pairs, for velocities no single frame shows) · student (readout recipe) · eval-student
# (held-out scenes, and those with camera, light and physics moved) · paper (the paper's
# recipe at its preset budget) · dreamer (Dreamer w/ DR for as long as the read-out trained) ·
# eval (every agent) · carry (D stripped of its images with its teacher's weights, the few MB
# from which `twist-data render --reproduce` rebuilds D on another machine).
#
# Environment (defaults in brackets):
#   FRAMES, LEARN   collection frames and the frames the teacher learns for [500000, 450000]
#   PRESET, COMPILE model sizes and schedule [quick], the compiled update [on]
#   DR              the collection's DR preset [train-wide]
#   EVAL_EVERY      frames between the teacher's evaluations [5000]: at `quick`'s 2,000 they
#                   take 11% of a long collection's wall time (benchmarks/teacher_profile.py)
#   TEACHER_SET     extra collection settings, e.g. "teacher.world_model.symlog=true"
#   DISTIL_SET      extra read-out settings, e.g. "readout_stage.units=teacher"
#   PAIRS           1: distil from D re-rendered with frame pairs [1]
#   EPISODES        held-out episodes per agent and preset [30]
#   STOP_AFTER      a step's name: stop after it
set -euo pipefail
TASK=${1:?usage: task.sh TASK OUT [SEED]}
OUT=${2:?usage: task.sh TASK OUT [SEED]}
SEED=${3:-0}
PRESET=${PRESET:-quick}
EPISODES=${EPISODES:-30}
D=$OUT/dataset
TEACHER=$D/collect/collect-000/teacher.pt
mkdir -p "$OUT"
log() { echo "$(date -u +%H:%M:%S) $*"; }
stop_after() { if [ "${STOP_AFTER:-}" = "$1" ]; then log "stopped after $1"; exit 0; fi; }
# "--set K=V" for each whitespace-separated K=V of $1, into the array named by $2.
settings() { local kv; local -n into=$2; into=(); read -ra kvs <<<"$1"
  for kv in "${kvs[@]}"; do into+=(--set "$kv"); done; }
done_or() { if [ -f "$OUT/$1.done" ]; then stop_after "$1"; return 0; fi; log "$1"; return 1; }
finish() { touch "$OUT/$1.done"; stop_after "$1"; }
settings "${TEACHER_SET:-}" teacher_set
settings "${DISTIL_SET:-}" distil_set

done_or collect || {
  twist-collect --task "$TASK" --preset "$PRESET" --out "$D" --frames "${FRAMES:-500000}" \
    --seed "$SEED" --dr "${DR:-train-wide}" --set learn_frames="${LEARN:-450000}" \
    --set compile="${COMPILE:-on}" --set eval_every="${EVAL_EVERY:-5000}" \
    ${teacher_set[@]+"${teacher_set[@]}"} --quiet --resume
  finish collect; }
done_or verify || { twist-data verify "$D" --rerender 20 | tee "$OUT/verify.txt"; finish verify; }

SOURCE=$D
if [ "${PAIRS:-1}" = 1 ]; then
  SOURCE=$OUT/paired
  done_or pairs || {
    rm -rf "$SOURCE"
    twist-data render "$D" "$SOURCE" --reproduce --pairs --workers "${WORKERS:-1}"
    finish pairs; }
fi

done_or student || {
  twist-distil --dataset "$SOURCE" --out "$OUT/ro" --preset "$PRESET" --recipe readout \
    --teacher "$TEACHER" ${distil_set[@]+"${distil_set[@]}"} --quiet --resume
  finish student; }
agents=(--agent "teacher=$TEACHER" --agent "student=$OUT/ro/agent.pt")
done_or eval-student || {
  twist-eval --task "$TASK" "${agents[@]}" --agent zero --dr heldout,heldout-full \
    --episodes "$EPISODES" --batch 10 --out "$OUT/eval-student" | tee "$OUT/eval-student.txt"
  finish eval-student; }

done_or paper || {
  twist-distil --dataset "$D" --out "$OUT/paper" --preset "$PRESET" --recipe paper \
    --teacher "$TEACHER" --quiet --resume
  finish paper; }
done_or dreamer || {
  # As long as the read-out trained: the same wall clock, this machine's.
  seconds=$(python -c "import json, math, sys
print(max(1, math.ceil(json.load(open(sys.argv[1]))['seconds'])))" "$OUT/ro/summary.json")
  twist-baseline --dataset "$D" --kind dreamer --preset "$PRESET" --steps 1000000 --time-limit "$seconds" \
    --out "$OUT/dreamer" --quiet --resume
  finish dreamer; }
done_or eval || {
  twist-eval --task "$TASK" "${agents[@]}" --agent "paper=$OUT/paper/agent.pt" \
    --agent "dreamer=$OUT/dreamer/agent.pt" --agent zero --dr heldout,heldout-full \
    --episodes "$EPISODES" --batch 10 --out "$OUT/eval" | tee "$OUT/eval.txt"
  finish eval; }
done_or carry || {
  rm -rf "$OUT/carry"
  twist-data strip "$D" "$OUT/carry" --teacher
  finish carry; }
log "done: $OUT/eval.txt, $OUT/carry"
