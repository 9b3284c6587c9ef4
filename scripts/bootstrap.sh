# Sourced by scripts/main.sh and scripts/test.sh: creates ./.venv on first use and
# installs the package into it. Safe to run again; it only installs what is missing.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${TWIST_VENV:-$ROOT/.venv}"
PYTHON="${PYTHON:-python3}"
if [ ! -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV"
fi
# shellcheck disable=SC1091
. "$VENV/bin/activate"
stamp="$VENV/.twist-installed"
if [ ! -f "$stamp" ] || [ "$ROOT/pyproject.toml" -nt "$stamp" ]; then
  # torch first, pinned: this version is a local CPU wheel here; an unpinned torch
  # would pull a multi-GB CUDA build.
  python -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
  python -m pip install --quiet --disable-pip-version-check "mujoco==3.17.0" -e "$ROOT[dev,sim,gym,video,lerobot,minari,torchrl,tensorboard,viz]"
  touch "$stamp"
fi
export MUJOCO_GL="${MUJOCO_GL:-egl}"
cd "$ROOT"
