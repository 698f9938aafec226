#!/usr/bin/env bash
# Run the test suite in the project's virtual environment (extra args go to pytest).
#   scripts/test.sh                 # everything (what CI runs)
#   scripts/test.sh -m "not slow"   # the fast subset
case "${1:-}" in
  -h|--help)
    cat <<'HELP'
usage: scripts/test.sh [pytest arguments ...]

Run torchfit's test suite (pytest, from the repository root) in the project's virtual
environment, creating or updating it first (scripts/_venv.sh). Writes nothing but pytest's
cache.

  scripts/test.sh                         # everything, what CI runs (about 36 minutes on 2 cores)
  scripts/test.sh -m "not slow"           # the fast part
  scripts/test.sh tests/experiments -x    # one folder, stop at the first failure
  scripts/test.sh -k simulate --durations=10

The arguments a TD uses: -m "not slow", a test file or folder (relative to the repository
root), -k <words>, -x. pytest's own help: scripts/test.sh --pytest-help.
Documented in docs/guide/install-and-run.md.
HELP
    exit 0 ;;
  --pytest-help) set -- --help ;;
esac
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
cd "$ROOT"
exec "$TORCHFIT_PYTHON" -m pytest "$@"
