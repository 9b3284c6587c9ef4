#!/usr/bin/env bash
# The test command: installs what it needs into ./.venv, lints, then runs the fast suite.
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
ruff check twist_data twist_models cli tests benchmarks research scripts
python -m pytest "$@"
