#!/usr/bin/env bash
# The whole boostnerf chain on a generated scene (no dataset needed), then pictures:
#   make-scene --content detail (48 px: fine detail on one half of the scene, smooth content on the other, the
#   scene where routing samples by resolution matters), then recipes/chain.sh with recipes/demo-dvgo-cpu.yaml
#   (pretrain -> build-moe -> finetune baseline, top1, top2, ens -> eval --report -> count-params), a comparison
#   image, per-expert and gate images, an orbit video.
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
bash "$HERE/chain.sh" demo-dvgo-cpu "$WS/scene" "$WS" --seed "$SEED"
boostnerf render --workspace "$WS" --compare --views 2 --device "$DEVICE"
boostnerf render --workspace "$WS" --model top2 --per-expert --views 2 --device "$DEVICE"
boostnerf render --workspace "$WS" --model top2 --path orbit --frames 48 --device "$DEVICE"
echo "done: $WS/reports/eval.md, $WS/renders/compare/, $WS/renders/top2/ (per-expert, gate, orbit video)"
