#!/usr/bin/env bash
# The whole chain (recipes/chain.sh) on a Tanks and Temples (NSVF-style layout) scene.
# Usage: bash recipes/tanks.sh SIZE DATA WS [PRETRAIN_OPTIONS...]   SIZE: cpu or paper (recipes/tanks-dvgo-SIZE.yaml)
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/chain.sh" "tanks-dvgo-${1:?SIZE: cpu or paper}" "${2:?DATA: the scene folder}" "${3:?WS: the workspace}" --format tanks "${@:4}"
