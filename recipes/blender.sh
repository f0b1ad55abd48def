#!/usr/bin/env bash
# The whole chain (recipes/chain.sh) on a Blender synthetic (transforms_{train,val,test}.json) scene.
# Usage: bash recipes/blender.sh SIZE DATA WS [PRETRAIN_OPTIONS...]   SIZE: cpu or paper (recipes/blender-dvgo-SIZE.yaml)
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/chain.sh" "blender-dvgo-${1:?SIZE: cpu or paper}" "${2:?DATA: the scene folder}" "${3:?WS: the workspace}" "${@:4}"
