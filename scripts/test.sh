#!/usr/bin/env bash
# The test command: installs what it needs into ./.venv, lints, then runs the fast suite.
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
ruff check twist_data twist_models cli tests benchmarks research scripts
# One worker per core (pytest-xdist; at most 8, each holds torch and MuJoCo), each taking whole
# modules, so that a module's fixtures are built once; a later -n in "$@" wins (-n 0: one
# process).
python -m pytest -n auto --maxprocesses 8 --dist loadscope "$@"
