#!/usr/bin/env bash
# Regenerates the README's contact sheets: per task, one state under train and held-out DR.
set -euo pipefail
. "$(dirname "$0")/bootstrap.sh"
for task in cartpole-balance cheetah-run cup-catch finger-turn_easy hopper-stand walker-walk \
            panda-push panda-lift; do
  twist-data contact-sheet "$task" "docs/images/contact-$task.png" --views 6 --seed 0
done
