# Installs twist from this repository and the wheels of scripts/offline_bundle.py on a machine
# with no package index, into the Python that holds its CUDA torch, then checks that every
# package twist needs is there at an accepted version (scripts/check_requirements.py).
#
#   . scripts/offline_install.sh DIR [TARGET]
#
# With TARGET the packages go to that folder instead of the environment (for a read-only
# image), and PYTHONPATH and PATH are exported to use them. Sourced, so that they stay set.
_wheels="${1:?usage: . scripts/offline_install.sh DIR [TARGET]}"
_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_python="${PYTHON:-python3}"
_where=()
if [[ -n "${2:-}" ]]; then
  _where=(--target "$2")
  export PYTHONPATH="$2${PYTHONPATH:+:$PYTHONPATH}" PATH="$2/bin:$PATH"
fi
"$_python" -m pip install --quiet --no-index --no-deps --no-build-isolation --no-compile \
  "${_where[@]}" "$_wheels"/*.whl "$_root" \
  && "$_python" "$_root/scripts/check_requirements.py" twist
