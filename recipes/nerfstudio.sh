#!/usr/bin/env bash
# The whole chain (recipes/chain.sh) on a nerfstudio transforms.json scene.
# Usage: bash recipes/nerfstudio.sh SIZE DATA WS [PRETRAIN_OPTIONS...]   SIZE: cpu or paper (recipes/nerfstudio-dvgo-SIZE.yaml)
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/chain.sh" "nerfstudio-dvgo-${1:?SIZE: cpu or paper}" "${2:?DATA: the scene folder}" "${3:?WS: the workspace}" --format nerfstudio "${@:4}"
