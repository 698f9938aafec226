#!/usr/bin/env bash
# Run the test suite in the project's virtual environment (extra args go to pytest).
#   scripts/test.sh                 # everything (what CI runs)
#   scripts/test.sh -m "not slow"   # the fast subset
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
cd "$ROOT"
exec "$TORCHFIT_PYTHON" -m pytest "$@"
