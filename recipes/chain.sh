#!/usr/bin/env bash
# The whole boostnerf chain for one scene, as users run it: `boostnerf chain` (pretrain -> build-moe -> finetune
# --baseline, --topk 1, --topk 2, --ensemble -> eval --report -> count-params -> render --compare -> a video).
#
# Usage: bash recipes/chain.sh RECIPE DATA WS [PRETRAIN_OPTIONS...]
#   RECIPE  a recipe file, or the name of one in recipes/ (blender-dvgo-cpu = recipes/blender-dvgo-cpu.yaml)
#   DATA    the scene folder, or - for the embedded procedural scene
#   WS      the workspace folder
#   PRETRAIN_OPTIONS set recipe keys for the run (e.g. --format llff, --image-size 200, --res 32,48,64, --seed 1,
#           --iters 300, --set KEY=VALUE); any other `boostnerf chain` option passes through (--frames 24)
# Environment: DEVICE (auto, cpu or cuda; default auto), MODELS (finetuned models to make; default
# "baseline top1 top2 ens"), TOP1_WEIGHT (renormalized, the default: Top-1's weight is 1; raw: the gate's
# probability, `finetune --topk 1 --no-renormalize`, as the official code weighs Top-1).
#
# Stops at the first failing stage and says which. Rerunnable: finished experts and models are skipped (an
# interrupted one resumes from its checkpoint); build-moe keeps an unchanged moe/init, eval and count-params run
# again (the reports cover the whole test split and every model), pictures newer than their models are kept.
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit 2
fi
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
RECIPE="$1" DATA="$2" WS="$3"
shift 3
case "$RECIPE" in  # a name: this folder's recipe (one not here is refused by boostnerf chain, which lists them)
  */*|*.yaml|*.yml) ;;
  *) [ ! -f "$HERE/$RECIPE.yaml" ] || RECIPE="$HERE/$RECIPE.yaml" ;;
esac

# pretrain's options that `boostnerf chain` has no option of its own for, as the recipe keys they set
OPTIONS=()
while [ $# -gt 0 ]; do
  opt="$1"
  case "$opt" in
    --skip) OPTIONS+=(--set pretrain.skip=true); shift; continue ;;
    --no-skip) OPTIONS+=(--set pretrain.skip=false); shift; continue ;;
    --iters|--model|--holdout-every|--iters=*|--model=*|--holdout-every=*)
      if [[ "$opt" == *=* ]]; then value="${opt#*=}"; opt="${opt%%=*}"; shift
      elif [ $# -ge 2 ]; then value="$2"; shift 2
      else echo "chain: $opt needs a value" >&2; exit 2
      fi
      case "$opt" in
        --iters) key=pretrain.iters ;;
        --model) key=pretrain.model ;;
        --holdout-every) key=data.holdout_every ;;
      esac
      OPTIONS+=(--set "$key=$value") ;;
    *) OPTIONS+=("$opt"); shift ;;
  esac
done

exec boostnerf chain "$DATA" --workspace "$WS" --recipe "$RECIPE" --device "${DEVICE:-auto}" \
  --models "${MODELS:-baseline top1 top2 ens}" --top1-weight "${TOP1_WEIGHT:-renormalized}" \
  ${OPTIONS[@]+"${OPTIONS[@]}"}
