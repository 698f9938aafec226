#!/usr/bin/env bash
# Run the test suite in the project's virtual environment (extra args go to pytest), on two
# pytest-xdist workers, and print the run's measured wall time at the end.
#   scripts/test.sh                 # everything (what CI runs)
#   scripts/test.sh --tier fast     # before each commit (tests/tiers.py)
#   scripts/test.sh -m "not slow"   # the tests not marked slow
case "${1:-}" in
  -h|--help)
    cat <<'HELP'
usage: scripts/test.sh [--tier fast|full] [pytest arguments ...]

Run torchfit's test suite (pytest, from the repository root) in the project's virtual
environment, creating or updating it first (scripts/_venv.sh), on two pytest-xdist workers
(both cores of a 2-core machine), and print the run's wall time and counts at the end.
Writes nothing but pytest's cache.

  scripts/test.sh --tier fast             # the fast tier: before each commit (about 5 minutes on 2 cores)
  scripts/test.sh                         # everything, what CI runs (--tier full, about 14 minutes on 2 idle cores)
  scripts/test.sh -m "not slow"           # the tests not marked slow
  scripts/test.sh tests/experiments -x    # one folder, stop at the first failure
  scripts/test.sh -k simulate --durations=10

The tiers are named in tests/tiers.py: fast is every test neither marked slow nor listed
there as too long for it; full is everything. The arguments a TD uses: --tier fast,
-m "not slow", a test file or folder (relative to the repository root), -k <words>, -x.
TORCHFIT_TEST_WORKERS=N: N workers (default 2; 1: one process, as pytest alone runs; also
without workers with -n, --pdb, --collect-only). pytest's own help: scripts/test.sh
--pytest-help. Documented in docs/guide/install-and-run.md.
HELP
    exit 0 ;;
  --pytest-help) set -- --help ;;
esac
tier=""
args=()
while [ $# -gt 0 ]; do
  case "$1" in
    --tier) tier="${2:-}"; shift 2 || { echo "scripts/test.sh: --tier needs a name (fast, full)" >&2; exit 2; } ;;
    --tier=*) tier="${1#--tier=}"; shift ;;
    *) args+=("$1"); shift ;;
  esac
done
selection=()
case "$tier" in
  fast) selection=(-m fast) ;;
  full|"") ;;
  *) echo "scripts/test.sh: unknown tier '$tier' (fast, full: tests/tiers.py)" >&2; exit 2 ;;
esac
workers="${TORCHFIT_TEST_WORKERS:-2}"
if ! [[ "$workers" =~ ^[0-9]+$ ]]; then
  echo "scripts/test.sh: TORCHFIT_TEST_WORKERS=$workers is not a number of workers" >&2
  exit 2
fi
measured=1
for a in "${args[@]}"; do
  case "$a" in        # the caller's own -n, or what xdist cannot do (a debugger, no run)
    -n*|--numprocesses|--numprocesses=*|no:xdist|-pno:xdist|--pdb|--trace|--collect-only|--co|--version|-V|--help|--fixtures|--markers)
      workers=0 ;;
  esac
  case "$a" in --collect-only|--co|--version|-V|--help|--fixtures|--markers) measured=0 ;; esac
done
distribute=()
if [ "$workers" -gt 1 ]; then
  distribute=(-n "$workers" --dist loadgroup)
fi
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
cd "$ROOT"
if [ "$measured" = 0 ]; then
  exec "$TORCHFIT_PYTHON" -m pytest "${selection[@]}" "${distribute[@]}" "${args[@]}"
fi
summary="$(mktemp)"
trap 'rm -f "$summary"' EXIT
start=$(date +%s)
set +e
TORCHFIT_TEST_SUMMARY="$summary" "$TORCHFIT_PYTHON" -m pytest "${selection[@]}" \
  "${distribute[@]}" "${args[@]}"
status=$?
set -e
seconds=$(( $(date +%s) - start ))
name="${tier:-full}"
if [ "${#args[@]}" -gt 0 ]; then
  name="$name (with ${args[*]})"
fi
where="$([ "$workers" -gt 1 ] && echo "$workers workers" || echo "one process")"
echo "tier $name: $((seconds / 60)) min $((seconds % 60)) s wall, $where on $(nproc) cores, pytest exit status $status"
if [ -s "$summary" ]; then
  echo "${tier:-full}: $(cat "$summary")"
fi
exit "$status"
