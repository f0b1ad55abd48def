#!/usr/bin/env bash
# The whole boostnerf chain on the embedded procedural scene (no dataset needed):
#   pretrain -> build-moe -> finetune (baseline, top1, top2) -> eval --report -> render
# Usage: bash recipes/quickstart.sh [WORKSPACE]   (default: ./ws-demo)
# Stops at the first failing stage; rerunning skips every stage that already finished.
set -euo pipefail
WS="${1:-ws-demo}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
RECIPE="$HERE/demo-dvgo-cpu.yaml"

boostnerf pretrain --workspace "$WS" --recipe "$RECIPE"
[ -f "$WS/moe/init.safetensors" ] || boostnerf build-moe --workspace "$WS" --recipe "$RECIPE"
boostnerf finetune --workspace "$WS" --recipe "$RECIPE" --baseline
boostnerf finetune --workspace "$WS" --recipe "$RECIPE" --topk 1
boostnerf finetune --workspace "$WS" --recipe "$RECIPE" --topk 2
boostnerf eval --workspace "$WS" --split test --report
boostnerf render --workspace "$WS" --model top2 --split test --views 2
echo "done: reports in $WS/reports, images in $WS/renders"
