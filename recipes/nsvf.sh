#!/usr/bin/env bash
# The whole chain (recipes/chain.sh) on a NSVF Synthetic (pose/, intrinsics.txt, rgb/) scene.
# Usage: bash recipes/nsvf.sh SIZE DATA WS [PRETRAIN_OPTIONS...]   SIZE: cpu or paper (recipes/nsvf-dvgo-SIZE.yaml)
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/chain.sh" "nsvf-dvgo-${1:?SIZE: cpu or paper}" "${2:?DATA: the scene folder}" "${3:?WS: the workspace}" --format nsvf "${@:4}"
