#!/usr/bin/env bash
# One short GPU slot: distil a student from a D collected elsewhere and measure its learning
# curve. Starts from a carry folder (scripts/gpu_carry.py: D stripped of its images, the
# teacher's weights, optionally the wheels and GL loaders a GPU image lacks), then
#   0. unpacks the carried GL loaders (CARRY/gl/*.deb, as root), without which EGL fails;
#   1. installs twist (the carried wheels into /tmp when the image has no package index);
#   2. rebuilds D's images from their stored physics and DR draws on every core
#      (twist-data render --reproduce; frames drawn by another GL than the one that recorded
#      D are accepted and counted in dataset/reproduction.json);
#   3. distils for STEPS updates or DISTIL_SECONDS, whichever ends first (compiled on a GPU),
#      keeping a deployable snapshot every SNAPSHOT_EVERY updates;
#   4. evaluates every snapshot, the teacher and the zero floor on EVAL_EPISODES held-out
#      episodes (twist-eval --snapshots: curve.csv, curve.png);
#   5. with FACTORS, evaluates the final student under each of those DR presets too
#      (twist-eval --dr FACTORS: factors.csv);
#   6. copies its result files to RESULTS (a slot returns at most eight): slot.json (stage
#      seconds, the rebuild's report, the distiller's summary), the distiller's metrics.csv
#      (window updates) and frame-metrics.csv (a first stage's), heldout.csv, curve.csv,
#      curve.png, episodes.csv, and factors.csv with FACTORS.
# Every stage resumes where it stopped: the same command in a later slot continues the run.
#
#   bash scripts/gpu_slot.sh CARRY [OUT]      # OUT defaults to runs/slot
#
# Settings (environment): DEVICE (cuda), PRESET (quick), RECIPE (paper), STEPS (window
# updates: 12000; with RECIPE=readout the preset's, which trains on single frames alone),
# SNAPSHOT_EVERY (2000), DISTIL_SECONDS (420), EVAL_EPISODES (10), WORKERS (processes that
# rebuild D: the cores), COMPILE (true on CUDA, false elsewhere), RESULTS ($OUT/results),
# DISTIL_SET (space-separated KEY=VALUE settings passed on as --set, e.g. frame_steps=20000),
# FACTORS (comma-separated DR presets, e.g. heldout,heldout-camera,heldout-full; none).
# PRESET=tiny DEVICE=cpu runs it at test sizes in seconds (tests/test_gpu_slot.py does).
set -euo pipefail
CARRY="${1:?usage: bash scripts/gpu_slot.sh CARRY [OUT]}"
OUT="${2:-runs/slot}"
CARRY="$(cd "$CARRY" && pwd)"
cd "$(dirname "$0")/.."
if compgen -G "$CARRY/gl/*.deb" >/dev/null && [[ "$(id -u)" == 0 ]]; then
  # A CUDA image without libEGL: MuJoCo's EGL context fails ("'NoneType' object has no
  # attribute 'eglQueryString'") until the carried loaders are unpacked and NVIDIA's vendor
  # file is named.
  for package in "$CARRY"/gl/*.deb; do dpkg -x "$package" /; done
  ldconfig
  vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  if [[ -f "$vendor" ]]; then export __EGL_VENDOR_LIBRARY_FILENAMES="${__EGL_VENDOR_LIBRARY_FILENAMES:-$vendor}"; fi
fi
if command -v twist-distil >/dev/null 2>&1; then
  export MUJOCO_GL="${MUJOCO_GL:-egl}"
elif [[ -d "$CARRY/wheels" ]]; then
  # A GPU image with its own CUDA torch and no package index: the carried wheels, into /tmp.
  . scripts/offline_install.sh "$CARRY/wheels" /tmp/twist-site
  export MUJOCO_GL="${MUJOCO_GL:-egl}"
else
  . scripts/bootstrap.sh
fi
. scripts/stages.sh
DEVICE="${DEVICE:-cuda}"
PRESET="${PRESET:-quick}"
RECIPE="${RECIPE:-paper}"
STEPS="${STEPS:-$([[ "$RECIPE" == readout ]] || echo 12000)}"
SNAPSHOT_EVERY="${SNAPSHOT_EVERY:-2000}"
EVAL_EPISODES="${EVAL_EPISODES:-10}"
RESULTS="${RESULTS:-$OUT/results}"
COMPILE="${COMPILE:-$([[ "$DEVICE" == cuda* ]] && echo true || echo false)}"
mkdir -p "$OUT"

if [[ ! -d "$OUT/dataset" ]]; then
  stage rebuild twist-data render "$CARRY/dataset" "$OUT/dataset" --reproduce \
        --workers "${WORKERS:-$(nproc)}" --accept-other-gl
fi

SETTINGS=(--set "schedule.snapshot_every=$SNAPSHOT_EVERY" --set "schedule.eval_every=$SNAPSHOT_EVERY"
          --set "schedule.checkpoint_every=$SNAPSHOT_EVERY" --set "compute.compile=$COMPILE")
for setting in ${DISTIL_SET:-}; do SETTINGS+=(--set "$setting"); done
RESUME=()
if [[ -f "$OUT/student/config.json" ]]; then RESUME=(--resume); fi
stage distil twist-distil --dataset "$OUT/dataset" --teacher "$CARRY/teacher.pt" \
      --out "$OUT/student" --preset "$PRESET" --recipe "$RECIPE" --device "$DEVICE" \
      ${STEPS:+--steps "$STEPS"} --time-limit "${DISTIL_SECONDS:-420}" --quiet "${SETTINGS[@]}" \
      "${RESUME[@]}" > "$OUT/distil-summary.json"

EVAL=(--episodes "$EVAL_EPISODES" --batch "$EVAL_EPISODES")
if [[ "$PRESET" == tiny ]]; then EVAL+=(--max-steps 20); fi
if [[ -f "$OUT/curve/episodes.csv" ]]; then EVAL+=(--resume); fi
stage curve twist-eval --snapshots "$OUT/student" --teacher "$CARRY/teacher.pt" --dr heldout \
      --device "$DEVICE" --out "$OUT/curve" --quiet "${EVAL[@]}" > /dev/null
if [[ -n "${FACTORS:-}" ]]; then
  FACTOR_EVAL=(--episodes "$EVAL_EPISODES" --batch "$EVAL_EPISODES")
  if [[ "$PRESET" == tiny ]]; then FACTOR_EVAL+=(--max-steps 20); fi
  if [[ -f "$OUT/factors/factors.csv" ]]; then FACTOR_EVAL+=(--resume); fi
  stage factors twist-eval --agent "student=$OUT/student/agent.pt" --dr "$FACTORS" \
        --device "$DEVICE" --out "$OUT/factors" --quiet "${FACTOR_EVAL[@]}" > /dev/null
fi

write_timings "$OUT/timings.json" "preset=$PRESET" "recipe=$RECIPE" "device=$DEVICE" \
  "updates=$(python -c 'import json, sys; print(json.load(sys.stdin)["updates"])' \
             < "$OUT/distil-summary.json")"
# One JSON of the slot (stage seconds, the rebuild's report, the distiller's summary) and the
# tables and plot: at most eight files, the most a slot returns.
python - "$OUT" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
parts = {"timings": out / "timings.json", "rebuild": out / "dataset" / "reproduction.json",
         "distil": out / "distil-summary.json"}
slot = {name: json.loads(path.read_text()) for name, path in parts.items() if path.exists()}
(out / "slot.json").write_text(json.dumps(slot, indent=2))
PY
mkdir -p "$RESULTS"
cp "$OUT/slot.json" "$OUT/student/heldout.csv" "$OUT/curve/curve.csv" "$OUT/curve/curve.png" \
   "$OUT/curve/episodes.csv" "$RESULTS/"
for table in "$OUT/student/metrics.csv" "$OUT/student/frame-metrics.csv" "$OUT/factors/factors.csv"; do
  if [[ -f "$table" ]]; then cp "$table" "$RESULTS/"; fi
done
cat "$OUT/timings.json"
echo "slot done: results in $RESULTS"
