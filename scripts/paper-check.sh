#!/usr/bin/env bash
# The paper-scale M = 3 chain on lego in one call of at most 9 minutes on one H200: does Top-1 beat its baseline at
# 800 px with 160^3-256^3 experts, and does any spatial partition of the experts beat the best of them
# (docs/results.md, "Why does Top-1 stay below its baseline at 100 px?")?
#
# Usage: bash scripts/paper-check.sh LEGO OUT
#   LEGO  the Blender lego scene (transforms_train.json + train/; every 8th view held out); OUT the work folder, kept:
#         run the same command again (on the same machine) and it goes on where the last call stopped.
#   DEVICE=cpu SCALE=tiny checks the script's logic on a CPU in minutes (40 px, experts 12/16/20, few steps). Every
#   setting is in scripts/gpucheck.py, SCALES["paper-check"], and an environment variable of its name overrides it:
#   BUDGET_S (540: stages still running then are stopped, marked CUT, and resumed by the next call), SPEED (1: the
#   speeds the plan assumes, as a fraction of the GPU speed targets, docs/gpu.md), FIXED_S, F_MIN, F_ROUND,
#   COST_VIEWS, ORACLE_*.
#   THREADS / COMPILE_THREADS as gpu-check.sh.
#
# The chain (recipes/blender-dvgo-paper-official.yaml: the official code's protocol at 800 px):
#  0. the plan, by the first call (OUT/plan.json, kept by later calls; scripts/gpucheck.py plan_chain): the joint
#     steps F of the baseline, Top-1 and Top-2, sized from the GPU speed targets on one H100 / H200 (lego, 8192
#     rays a step: a DVGO-160 step at 5 M rays/s, a DVGO step's seconds growing with its grid's side as its samples
#     per ray do; a Top-1 / Top-2 step 2.5x its largest expert's; an 800 px dvgo-160 image in 0.1 s), times SPEED:
#         F = (BUDGET_S - FIXED_S - pretraining - s_image * renders) / (s_baseline + s_top1 + s_top2),
#     rounded down to F_ROUND, within [F_MIN, the recipe's 20,000]. The three finetunes share the one GPU, so their
#     steps add up. FIXED_S (120 s) holds what does not scale with steps, on the chain's longest path: five process
#     start-ups (part (a) of gpu-check.sh on an H200: 4-12 s a whole tiny stage), decoding 100 lego views at 800 px
#     once (the scene cache serves the rest), build-moe, a finetune's first compile, four 5 GB mixture checkpoints.
#     At the targets F = 20,000 (the official count) fits with about 20 s to spare; at lower speeds (SPEED < 1) F
#     shrinks to F_MIN (1,000), and the plan says when that does not fit: then a second call finishes the chain;
#  1. the coarse geometry and dvgo-160 in OUT/ws; once the geometry is written, dvgo-200 and dvgo-256 each in a
#     workspace of its own, all three at once (1,000 steps each, the official count); their files linked into OUT/ws;
#  2. build-moe (the gate copied from dvgo-160);
#  3. at once: finetune --baseline, --topk 1 --no-renormalize (the official Top-1 weight) and --topk 2 with
#     --iters F, each in its own copy of OUT/ws, each then evaluated there (eval --no-costs on the 13 held-out views,
#     count-params --views COST_VIEWS for GFLOPs and ||w||_0); the experts' eval; research/partition_oracle.py on the
#     three experts (--map-res ORACLE_MAP_RES --train-views ORACLE_TRAIN_VIEWS);
#  4. OUT/paper-check.md: the plan, the held-out table (PSNR and GFLOPs against the baseline, training speed, start-up,
#     GPU utilisation) and the oracle's table; OUT/stages.md: every stage with its `ready in` and GPU utilisation
#     (nvidia-smi every 0.5 s).
# Resumable: every stage skips what is finished and resumes an interrupted model from its last checkpoint (every
# 500 pretraining and 5,000 joint steps); a later call keeps the plan and moves the earlier call's stage records to
# OUT/call-N/. Exits 0 when the chain is complete, non-zero while anything failed or is left for another call.
set -uo pipefail
NAME=paper-check
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/gpucheck-lib.sh
. "$HERE/scripts/gpucheck-lib.sh"
gc_begin 2 12 "$@"
LEGO="$(gc_abs "$1")"
OUT="$2"
if [ ! -f "$LEGO/transforms_train.json" ]; then
  echo "paper-check: $1 holds no transforms_train.json: give the Blender lego scene folder" >&2
  exit 2
fi
eval "$("$PY" "$G" settings paper-check "$SCALE")"  # BUDGET_S COST_VIEWS ORACLE_MAP_RES ORACLE_TRAIN_VIEWS
mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
if [ -s "$OUT/stages.tsv" ]; then  # an earlier call's records: kept aside
  n=1
  while [ -e "$OUT/call-$n" ]; do n=$((n + 1)); done
  mkdir -p "$OUT/call-$n"
  mv "$OUT/stages.tsv" "$OUT/logs" "$OUT/call-$n/"
  [ -f "$OUT/stages.md" ] && mv "$OUT/stages.md" "$OUT/call-$n/"
  [ -f "$OUT/util.csv" ] && mv "$OUT/util.csv" "$OUT/call-$n/"
fi
R="$OUT/recipe.yaml"
read -r -a RES < <("$PY" "$G" recipe paper-check "$SCALE" "$HERE/recipes/blender-dvgo-paper-official.yaml" "$R")
W="$OUT/ws"
gc_start

# ---- 0: the plan, once ----------------------------------------------------------------------------------------------
if [ -f "$OUT/plan.json" ]; then
  "$PY" "$G" describe-plan "$OUT/plan.json" >"$OUT/plan.md"
else
  "$PY" "$G" plan paper-check "$SCALE" "$R" "$LEGO" "$OUT/plan.json" >"$OUT/plan.md" ||
    { echo "paper-check: no plan could be made" >&2; exit 1; }
fi
cat "$OUT/plan.md"
F="$("$PY" -c "import json, sys; print(json.load(open(sys.argv[1]))['iters'])" "$OUT/plan.json")"

# ---- 1-2: the experts, the untrained mixture ------------------------------------------------------------------------
EXPERTS=()
for r in "${RES[@]}"; do EXPERTS+=("dvgo-$r"); done
pretrain_experts "(1)" "$W" "$R" "$LEGO" dvgo "${RES[@]}" ||
  gc_finish "the experts are not all trained: run the same command again to go on" incomplete
if [ -f "$W/moe/init.json" ]; then
  echo "(2) build-moe: moe/init was built by an earlier call"
else
  check "(2) build-moe" "${BN[@]}" build-moe -w "$W" --recipe "$R" --device "$DEV" || gc_finish "" incomplete
fi
for m in baseline top1 top2 experts; do copy_ws "$W" "$W-$m"; done  # before any finetune writes into one

# ---- 3: the finetunes, the evals and the oracle, at once -------------------------------------------------------------
pids=()
if [ ! -f "$OUT/partition-oracle.json" ]; then
  models=()
  for e in "${EXPERTS[@]}"; do models+=(--model "$e=$W"); done
  oracle_stage "(3) partition oracle" "$OUT/partition-oracle.json" "${models[@]}" --map-res "$ORACLE_MAP_RES" \
    --train-views "$ORACLE_TRAIN_VIEWS" &
  pids+=($!)
fi
evaluate() {  # evaluate LABEL WS MODEL...: eval on every held-out view, count-params on COST_VIEWS, once each
  local label="$1" ws="$2"
  shift 2
  local names=() m
  for m in "$@"; do names+=(--model "$m"); done
  { [ -f "$ws/reports/eval.json" ] ||
      check "(3) eval $label" "${BN[@]}" eval -w "$ws" "${names[@]}" --no-costs --report --device "$DEV"; } &&
    { [ -f "$ws/reports/count-params.json" ] ||
      check "(3) count-params $label" "${BN[@]}" count-params -w "$ws" "${names[@]}" --views "$COST_VIEWS" \
        --device "$DEV"; }
}
evaluate experts "$W-experts" "${EXPERTS[@]}" &
pids+=($!)
for m in baseline top1 top2; do
  case $m in
    baseline) flag=(--baseline) ;;
    top1) flag=(--topk 1 --no-renormalize) ;;  # the official code's Top-1 weight: the gate's raw probability
    top2) flag=(--topk 2) ;;
  esac
  {
    check "(3) finetune $m" "${BN[@]}" finetune -w "$W-$m" --recipe "$R" "${flag[@]}" --iters "$F" --device "$DEV" &&
      evaluate "$m" "$W-$m" "$m"
  } &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done

# ---- 4: the tables ---------------------------------------------------------------------------------------------------
{
  echo "# paper-check: M = 3 at 800 px (lego, every 8th view held out)"
  echo
  "$PY" "$G" device "$DEV"
  echo "recipe $R (recipes/blender-dvgo-paper-official.yaml with scripts/gpucheck.py's $SCALE settings); Top-1 with" \
    "the official raw-probability weight (--no-renormalize)"
  echo
  cat "$OUT/plan.md"
  echo
} >"$OUT/paper-check.md"
rows=()
for e in "${EXPERTS[@]}"; do
  stage="(1) pretrain $e"
  [ "$e" = "${EXPERTS[0]}" ] && stage="(1) pretrain geometry + $e"
  rows+=(--model "$e" "$W-experts" "$stage")
done
for m in baseline top1 top2; do rows+=(--model "$m" "$W-$m" "(3) finetune $m"); done
"$PY" "$G" models "$OUT/paper-check.md" --out "$OUT" --recipe "$R" --cost-views "$COST_VIEWS" "${rows[@]}" \
  >/dev/null || echo "paper-check: the held-out table could not be written" >&2
[ -f "$OUT/partition-oracle.json" ] && "$PY" "$G" table "$OUT/partition-oracle.json" "$OUT/paper-check.md" \
  "Partitions of the three experts on held-out views (research/partition_oracle.py)" >/dev/null
echo
cat "$OUT/paper-check.md"
done=1
for m in baseline top1 top2; do [ -f "$W-$m/reports/count-params.json" ] || done=0; done
[ -f "$W-experts/reports/count-params.json" ] && [ -f "$OUT/partition-oracle.json" ] || done=0
if [ $done = 1 ]; then
  gc_finish "the chain is complete: $OUT/paper-check.md"
fi
gc_finish "not finished in this call: run the same command again (on the same machine) to go on from here" incomplete
