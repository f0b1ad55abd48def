#!/usr/bin/env bash
# The whole boostnerf chain on the embedded procedural scene (no dataset needed), then pictures:
#   recipes/chain.sh with recipes/demo-dvgo-cpu.yaml (pretrain -> build-moe -> finetune baseline, top1,
#   top2, ens -> eval --report -> count-params), a comparison image, per-expert and gate images, an orbit video.
# Usage: bash recipes/quickstart.sh [WORKSPACE]   (default: ./ws-demo)
# Stops at the first failing stage; rerunning skips every model that already finished.
set -euo pipefail
WS="${1:-ws-demo}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
bash "$HERE/chain.sh" demo-dvgo-cpu - "$WS"
DEVICE="${DEVICE:-auto}"
boostnerf render --workspace "$WS" --compare --views 2 --device "$DEVICE"
boostnerf render --workspace "$WS" --model top2 --per-expert --views 2 --device "$DEVICE"
boostnerf render --workspace "$WS" --model top2 --path orbit --frames 48 --device "$DEVICE"
echo "done: $WS/reports/eval.md, $WS/renders/compare/, $WS/renders/top2/ (per-expert, gate, orbit video)"
