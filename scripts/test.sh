#!/usr/bin/env bash
# The test command: installs what it needs into ./.venv, lints, then runs the fast suite.
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
ruff check twist_data twist_models cli tests benchmarks research scripts
# One worker per core (pytest-xdist), each taking whole modules, so that a module's fixtures
# are built once; a later -n in "$@" wins, e.g. -n 0 for one process.
python -m pytest -n auto --dist loadscope "$@"
