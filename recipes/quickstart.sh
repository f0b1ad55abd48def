#!/usr/bin/env bash
# The whole boostnerf chain on the embedded procedural scene (no dataset needed):
#   pretrain -> eval --report -> render
# Usage: bash recipes/quickstart.sh [WORKSPACE]   (default: ./ws-demo). Rerunning skips finished stages.
set -euo pipefail
WS="${1:-ws-demo}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
RECIPE="$HERE/demo-dvgo-cpu.yaml"

boostnerf pretrain --workspace "$WS" --recipe "$RECIPE"
boostnerf eval --workspace "$WS" --split test --report
boostnerf render --workspace "$WS" --split test --views 2
echo "done: reports in $WS/reports, images in $WS/renders"
