#!/usr/bin/env bash
# The reference environment: other projects' own readers, which the tests run against twist's
# outputs (tests/test_lerobot.py, the statistics test in tests/test_eval.py). They pin what
# twist's environment cannot hold (lerobot-dataset: av<16, datasets<4.2; rliable: arch<8,
# which imports only beside pandas<3), so they live in their own venv, .venv-ref, made by
# .venv's Python and seeing .venv (torch) behind its own packages. Safe to run again; best
# effort: where it did not install, the tests that need it skip, saying why, and a failed
# install is not retried until this script changes.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
MAIN="${TWIST_VENV:-$ROOT/.venv}"
REF="${TWIST_REFERENCE_VENV:-$ROOT/.venv-ref}"
stamp="$REF/.twist-reference" failed="$REF/.twist-reference-failed"
for mark in "$stamp" "$failed"; do
  if [ -f "$mark" ] && [ "$mark" -nt "$0" ] && [ "$mark" -nt "$MAIN/bin/python" ]; then
    [ "$mark" = "$stamp" ]; exit
  fi
done
if [ -e "$REF" ] && [ ! -f "$REF/pyvenv.cfg" ]; then
  echo "$REF exists and is not a venv; not replaced" >&2
  exit 1
fi
rm -rf "$REF"
"$MAIN/bin/python" -m venv "$REF"
site="$("$MAIN/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
ref_site="$("$REF/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
echo "$site" > "$ref_site/zz-twist-venv.pth"  # last on sys.path: the reference's own win
pip=("$REF/bin/python" -m pip install --quiet --disable-pip-version-check --retries 1 --timeout 30)
if "${pip[@]}" "lerobot-dataset==0.4.4" "rliable==1.2.0" "pandas<3" &&
   # ledataset imports torchvision; this one is built for torch 2.13 (its ops need CUDA torch,
   # and tests/lerobot_readback.py stands in for the two its import registers).
   "${pip[@]}" --no-deps "torchvision==0.28.0"; then
  touch "$stamp"
else
  touch "$failed"
  exit 1
fi
