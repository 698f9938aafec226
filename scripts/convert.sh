#!/usr/bin/env bash
# Convert a rigged animation between the folder format, a USD UsdSkel stage and a glTF skin
# (torchfit/mesh/formats/convert.py; the output's suffix chooses the format).
#   scripts/convert.sh shot.usdc shot.glb
#   scripts/convert.sh my_arm arm.usda            # an animation folder to USD
#   scripts/convert.sh rig.glb rig_folder --fps 30
source "$(dirname "${BASH_SOURCE[0]}")/_venv.sh"
exec "$TORCHFIT_PYTHON" -m torchfit.mesh.formats.convert "$@"
