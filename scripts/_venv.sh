# Sourced by scripts/fit.sh and scripts/test.sh: create or reuse the project's virtual
# environment and install torchfit with the pinned versions of constraints.txt.
# Re-installs only when pyproject.toml or constraints.txt changed.
# Variables: TORCHFIT_VENV (default <repo>/.venv), PYTHON (default: python3.11 or python3),
# TORCHFIT_EXTRAS (default "dev,usd,gltf,amg,pardiso" on x86-64, "dev,usd,gltf,amg" elsewhere: MKL has no
# other wheels; usd (about 210 MB) and gltf so that CI runs the USD and glTF readers' tests),
# TORCHFIT_BLENDER (default 1 on x86-64 Linux with Python 3.11: Blender as a Python module,
# the extra blender, for the tests that round-trip rigs through Blender; 0 leaves it out).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${TORCHFIT_VENV:-$ROOT/.venv}"
if [ -z "${PYTHON:-}" ]; then
  PYTHON="$(command -v python3.11 || command -v python3)"
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
  echo "torchfit needs Python >= 3.10; set PYTHON=/path/to/python3.10+" >&2
  exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "[torchfit] creating virtual environment $VENV" >&2
  "$PYTHON" -m venv "$VENV"
fi
if [ -z "${TORCHFIT_EXTRAS:-}" ]; then
  case "$(uname -m)" in
    x86_64|AMD64) TORCHFIT_EXTRAS="dev,usd,gltf,amg,pardiso" ;;
    *) TORCHFIT_EXTRAS="dev,usd,gltf,amg" ;;
  esac
fi
if [ -z "${TORCHFIT_BLENDER:-}" ]; then
  TORCHFIT_BLENDER=0
  if [ "$(uname -s)" = Linux ] && [ "$(uname -m)" = x86_64 ] && \
      "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    TORCHFIT_BLENDER=1
  fi
fi
STAMP="$VENV/.torchfit-install"
WANT="$( (cat "$ROOT/pyproject.toml" "$ROOT/constraints.txt"; echo "$TORCHFIT_EXTRAS $TORCHFIT_BLENDER") | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$STAMP" 2>/dev/null || true)" != "$WANT" ]; then
  echo "[torchfit] installing torchfit and pinned dependencies into $VENV" >&2
  # torch is pinned (2.13.0, CPU build): an unpinned torch would pull several GB of CUDA.
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
    -c "$ROOT/constraints.txt" -e "$ROOT[$TORCHFIT_EXTRAS]" >&2
  if [ "$TORCHFIT_BLENDER" = 1 ]; then
    # the extra blender without its numpy<2 requirement (pyproject.toml says why)
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
      -c "$ROOT/constraints.txt" bpy >&2
  fi
  echo "$WANT" > "$STAMP"
fi
TORCHFIT_PYTHON="$VENV/bin/python"
