#!/usr/bin/env bash
# The whole boostnerf chain for one scene, as users run it:
#   pretrain -> build-moe -> finetune --baseline, --topk 1, --topk 2, --ensemble -> eval --report -> count-params
#
# Usage: bash recipes/chain.sh RECIPE DATA WS [PRETRAIN_OPTIONS...]
#   RECIPE  a recipe file, or the name of one in recipes/ (blender-dvgo-cpu = recipes/blender-dvgo-cpu.yaml)
#   DATA    the scene folder, or - for the embedded procedural scene
#   WS      the workspace folder
#   PRETRAIN_OPTIONS are passed to pretrain only (e.g. --format llff, --image-size 200, --device cpu)
# Environment: DEVICE (auto, cpu or cuda; default auto), MODELS (finetuned models to make; default
# "baseline top1 top2 ens"), TOP1_WEIGHT (renormalized, the default: Top-1's weight is 1; raw: the gate's
# probability, `finetune --topk 1 --no-renormalize`, as the official code weighs Top-1).
#
# Stops at the first failing stage (set -euo pipefail) and says which. Rerunnable: pretrain and
# finetune skip the models they already finished (and resume an interrupted one from its
# checkpoint); build-moe, eval and count-params run again (seconds to minutes): build-moe rebuilds a
# bit-identical moe/init from unchanged experts and settings, so the finished mixtures stay current,
# and the reports always cover the whole test split and every model.
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit 2
fi
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
RECIPE="$1" DATA="$2" WS="$3"
shift 3
DEVICE="${DEVICE:-auto}"
MODELS="${MODELS:-baseline top1 top2 ens}"
TOP1_WEIGHT="${TOP1_WEIGHT:-renormalized}"
case "$RECIPE" in
  */*|*.yaml|*.yml) ;;
  *) RECIPE="$HERE/$RECIPE.yaml" ;;
esac
if [ ! -f "$RECIPE" ]; then
  echo "chain: recipe $RECIPE not found; recipes here: $(cd "$HERE" && ls ./*.yaml | sed 's|^\./||; s|\.yaml$||' | tr '\n' ' ')" >&2
  exit 2
fi
for m in $MODELS; do  # before any stage: a typo found after an hour of pretraining costs the hour's attention
  case "$m" in
    baseline|ens|top[1-9]|top[1-9][0-9]) ;;
    *) echo "chain: unknown model $m in MODELS (use baseline, topK, ens)" >&2; exit 2 ;;
  esac
done
case "$TOP1_WEIGHT" in
  renormalized) TOP1=() ;;
  raw) TOP1=(--no-renormalize) ;;
  *) echo "chain: unknown TOP1_WEIGHT $TOP1_WEIGHT (use renormalized or raw)" >&2; exit 2 ;;
esac
DATA_ARGS=()
[ "$DATA" = "-" ] || DATA_ARGS=(--data "$DATA")

stage() {  # stage NAME COMMAND...: run one stage, name it when it fails
  echo "== chain: $1" >&2
  shift
  if ! "$@"; then
    echo "chain: stage failed: $(printf '%q ' "$@")" >&2  # quoted: pasted back, it reruns the stage
    exit 1
  fi
}

stage pretrain boostnerf pretrain --workspace "$WS" "${DATA_ARGS[@]}" --recipe "$RECIPE" --device "$DEVICE" "$@"
stage build-moe boostnerf build-moe --workspace "$WS" --recipe "$RECIPE" --device "$DEVICE"
for m in $MODELS; do
  case "$m" in
    baseline) flag=(--baseline) ;;
    ens) flag=(--ensemble) ;;
    top1) flag=(--topk 1 "${TOP1[@]}") ;;
    *) flag=(--topk "${m#top}") ;;  # topK, checked above
  esac
  stage "finetune $m" boostnerf finetune --workspace "$WS" --recipe "$RECIPE" "${flag[@]}" --device "$DEVICE"
done
stage eval boostnerf eval --workspace "$WS" --split test --report --device "$DEVICE"
stage count-params boostnerf count-params --workspace "$WS" --split test --device "$DEVICE"
echo "chain: done. Table: $WS/reports/eval.md; counts: $WS/reports/count-params.json" >&2
