#!/usr/bin/env bash
# The whole boostnerf chain on a generated scene (no dataset needed), then pictures:
#   make-scene --content detail (48 px: fine detail on one half of the scene, smooth content on the other, the
#   scene where routing samples by resolution matters), then `boostnerf chain` with recipes/demo-dvgo-cpu.yaml
#   (pretrain -> build-moe -> finetune baseline, top1, top2, ens -> eval --report -> count-params -> a comparison
#   image -> an orbit video of top2), then per-expert and gate images of top2.
# Usage: bash recipes/quickstart.sh [WORKSPACE]   (default: ./ws-demo; the scene goes to WORKSPACE/scene)
# Environment: DEVICE (auto, cpu or cuda; default auto), SEED (the scene's and the experts' seed; default 0).
# Stops at the first failing stage; rerunning skips every model that already finished.
set -euo pipefail
WS="${1:-ws-demo}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
DEVICE="${DEVICE:-auto}"
SEED="${SEED:-0}"
# make-scene writes the folder whole or not at all, so one that exists is complete: a rerun keeps it
[ -d "$WS/scene" ] || boostnerf make-scene "$WS/scene" --size 48 --content detail --seed "$SEED"
boostnerf chain "$WS/scene" --workspace "$WS" --recipe "$HERE/demo-dvgo-cpu.yaml" --seed "$SEED" --device "$DEVICE" \
  --video-model top2
boostnerf render --workspace "$WS" --model top2 --per-expert --views 2 --device "$DEVICE"
echo "done: $WS/reports/eval.md, $WS/renders/compare/, $WS/renders/top2/ (per-expert, gate, orbit video)"
