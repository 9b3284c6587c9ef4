#!/usr/bin/env bash
# The test command: installs what it needs into ./.venv, lints, then runs the fast suite.
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
# Other projects' own readers (LeRobot's loader, rliable), in their own venv, for the tests
# that check twist's outputs against them; where they cannot install, those tests skip.
if ! log="$(bash scripts/reference_env.sh 2>&1)"; then
  printf '%s\n' "$log" | tail -n 3
  echo "scripts/reference_env.sh failed: the tests against LeRobot and rliable skip"
fi
ruff check twist_data twist_sim twist_models twist_pipeline twist_cli tests benchmarks research scripts
# One worker per core (pytest-xdist; at most 8, each holds torch and MuJoCo), each taking whole
# modules, so that a module's fixtures are built once; a later -n in "$@" wins (-n 0: one
# process).
python -m pytest -n auto --maxprocesses 8 --dist loadscope "$@"
