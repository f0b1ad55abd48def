#!/usr/bin/env bash
# The whole chain (recipes/chain.sh) on a LLFF forward-facing (poses_bounds.npy + images/) scene.
# Usage: bash recipes/llff.sh SIZE DATA WS [PRETRAIN_OPTIONS...]   SIZE: cpu or paper (recipes/llff-dvgo-SIZE.yaml)
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/chain.sh" "llff-dvgo-${1:?SIZE: cpu or paper}" "${2:?DATA: the scene folder}" "${3:?WS: the workspace}" --format llff "${@:4}"
