#!/usr/bin/env bash
# Run the main job (experiments/fit.py) in the project's virtual environment.
#   scripts/fit.sh                                     # the short arm (arm3d_short), under a minute
#   scripts/fit.sh solver=levenberg_marquardt problem.noise=1e-4
#   scripts/fit.sh -m solver=gauss_newton,levenberg_marquardt hydra/launcher=joblib
#   scripts/fit.sh --standalone --nproc_per_node=2 problem=arm3d   # torchrun (experiments/launch.py)
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
# no cd: relative paths and the default outputs/ are those of the directory it is run from
case "${1:-}" in
  --standalone|--nproc[-_]per[-_]node=*|--nnodes=*|--rdzv[-_]*|--node[-_]rank=*|--master[-_]*)
    TORCHFIT_LAUNCHER=scripts/fit.sh exec "$TORCHFIT_PYTHON" "$ROOT/experiments/launch.py" "$@" ;;
esac
exec "$TORCHFIT_PYTHON" "$ROOT/experiments/fit.py" "$@"
