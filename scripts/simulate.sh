#!/usr/bin/env bash
# Use a fitted material (experiments/simulate.py) in the project's virtual environment.
#   scripts/simulate.sh run=<fitted run>                                  # the fit's animation
#   scripts/simulate.sh run=<arm run> problem.max_flexion=90 problem.n_frames=12 problem.frames=null
#   scripts/simulate.sh run=<run> problem.path=<another animation of the same body>
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
# no cd: relative paths and the default outputs/ are those of the directory it is run from
exec "$TORCHFIT_PYTHON" "$ROOT/experiments/simulate.py" "$@"
