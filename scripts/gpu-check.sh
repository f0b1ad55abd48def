#!/usr/bin/env bash
# Checks boostnerf on a CUDA GPU in one invocation of at most 8 minutes, with nothing but the project and a scene.
#
# Usage: bash scripts/gpu-check.sh SCENE [OUT]
#   SCENE  a Blender-layout scene (e.g. nerf_synthetic/lego); OUT the work folder (default ./gpu-check; emptied first)
#   QUICK=1 runs part (a) only (PARTS=b: part (b) only). DEVICE=cpu runs the same commands on the CPU; with
#   SCALE=tiny (part (b) at 40 px, experts 12/16/20, few steps) it checks this script's logic in minutes. BUDGET_S:
#   the time budget (480 s; stages still running then are stopped and marked CUT). THREADS / COMPILE_THREADS: CPU
#   threads / inductor compile workers per process (an eighth / a quarter of the cores). PROFILE=0/1:
#   step_profile.py's table (on for CUDA). Settings per scale: scripts/gpucheck.py, SCALES.
#
# (a) every stage and family on a tiny generated scene: pretrain, build-moe, finetune (top1, top2, baseline, ensemble),
#     eval (--device auto), count-params, render (views, --compare, --per-expert, --path orbit), prune, resume of an
#     interrupted run, TensoRF and Instant-NGP mixtures, bench, torchrun (one process), recipes/quickstart.sh;
# (b) a short chain on SCENE at 400 px (recipes/blender-dvgo-paper-gpucheck.yaml: DVGO experts 96/128/160, 3000 steps
#     each; baseline, Top-1, Top-2 and the ensemble 1000 joint steps each): held-out PSNR, GFLOPs per image, training
#     rays per second, s per image, start-up and GPU utilisation, as a markdown table in OUT/gpu-check.md; then
#     whether any spatial partition of the three experts beats the best of them on held-out views
#     (research/partition_oracle.py); then scripts/step_profile.py's table (--device cuda, compile on).
#
# Everything runs at once in independent groups, part (b) first (its chain is the longest): the three family chains of
# part (a) (the DVGO one fans out into four workspace copies after build-moe), bench, torchrun, quickstart, the step
# profile; in part (b) the geometry, then the three experts in workspaces of their own, then the four finetunes, each
# with its eval, in copies of the workspace, beside the experts' eval and the partition oracle. A writer locks its
# workspace (docs/stages.md), so concurrent writers always work in copies (hard links: stages replace files, never
# write into them). Part (a) runs at a lower CPU priority (nice 5) than part (b).
#
# Sizing, from the stage times of part (a) and of the 400 px chain measured on an H200 (one stage at a time; the
# GPU 30-60% busy while one expert trained), for part (b)'s longest path: geometry 27 s; the three experts at once,
# 23-31 s of training each alone (0.8-1.1 M rays/s), about 60 s; build-moe 5 s; the four finetunes at once, 1000
# steps each (half the recipe's 2000): the baseline 32 ms a step, a mixture step about 6x an expert's 10 ms (the
# ratio of part (a)'s tiny runs), so 30-60 s each alone, about 210 s if they shared the GPU with no overlap at all;
# eval and count-params of a model, 13 views at 0.4-0.7 s, 2 renders a mixture view: 20-40 s; five process
# start-ups on that path at 5-10 s each (part (a)'s whole tiny stages took 4-12 s). About 380 s at those speeds; part
# (a) runs beside it (its longest group, quickstart.sh, took 112 s alone). BUDGET_S (480 s) is a hard stop: a stage
# still running then is CUT.
#
# Prints one OK/FAIL/CUT line per stage as it ends, with its `ready in` lines and its torch.compile seconds; at the end
# a table of every stage (start, wall time, how many others ran beside it, ready in, compile, the device's mean / max
# utilisation and memory over its window, sampled by nvidia-smi every 0.5 s) -> OUT/stages.md. Exits non-zero on any
# failure or stage cut at the budget, and at once, with one line, when torch sees no CUDA GPU (unless DEVICE=cpu).
set -uo pipefail
NAME=gpu-check
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# shellcheck source=scripts/gpucheck-lib.sh
. "$HERE/scripts/gpucheck-lib.sh"
gc_begin 1 10 "$@"
SCENE="$(gc_abs "$1")"
OUT="${2:-gpu-check}"
if [ ! -d "$SCENE" ]; then
  echo "gpu-check: scene folder $1 does not exist" >&2
  exit 2
fi
eval "$("$PY" "$G" settings gpu-check-b "$SCALE")"  # BUDGET_S COST_VIEWS ORACLE_ARGS PROFILE_ARGS, unless set
mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
rm -rf "$OUT/tiny" "$OUT/b" "$OUT/logs" "$OUT/profile" "$OUT"/*.md "$OUT"/*.json "$OUT"/util.csv
gc_start
TINY="$OUT/tiny"
RESUME_ITERS=$([ "$SCALE" = tiny ] && echo 300 || echo 4000)

# ---- (a) every stage and family on a tiny scene ---------------------------------------------------------------------
group_dvgo() {  # the DVGO chain: after build-moe, four copies of the workspace run side by side
  local W="$TINY/ws-dvgo" D=(--device "$DEV")
  check "(a) dvgo pretrain" "${BN[@]}" pretrain -w "$W" --data "$TINY/scene" --recipe "$TINY/dvgo.yaml" "${D[@]}" ||
    return
  copy_ws "$W" "$W-resume"
  # resume: stop a longer run of a third expert (SIGINT, as Ctrl-C) once it wrote its first checkpoint, rerun it: it
  # resumes there (waiting for the file, not a fixed time: a fast GPU finishes the run in seconds)
  check "(a) dvgo resume from a checkpoint" bash -c "
    ${BN[*]} pretrain -w '$W-resume' --data '$TINY/scene' --recipe '$TINY/dvgo.yaml' --res 32 --iters $RESUME_ITERS \
      --device $DEV >/dev/null 2>&1 &
    pid=\$!
    for _ in \$(seq 3000); do
      test -f '$W-resume/checkpoints/dvgo-32.pt' && break; kill -0 \$pid 2>/dev/null || break; sleep 0.1
    done
    kill -INT \$pid 2>/dev/null; wait \$pid
    test -f '$W-resume/checkpoints/dvgo-32.pt' ||
      { echo 'no checkpoint left: the run ended before it could be stopped'; exit 1; }
    ${BN[*]} pretrain -w '$W-resume' --data '$TINY/scene' --recipe '$TINY/dvgo.yaml' --res 32 --iters $RESUME_ITERS \
      --device $DEV 2>&1 | tee /dev/stderr | grep -q 'resuming from'" &
  if check "(a) dvgo build-moe" "${BN[@]}" build-moe -w "$W" "${D[@]}"; then
    copy_ws "$W" "$W-top1"
    copy_ws "$W" "$W-base"
    {
      check "(a) dvgo finetune top2" "${BN[@]}" finetune -w "$W" --topk 2 "${D[@]}" &&
        check "(a) dvgo render" "${BN[@]}" render -w "$W" --model top2 "${D[@]}" &&
        check "(a) dvgo render --per-expert" "${BN[@]}" render -w "$W" --model top2 --per-expert --views 1 "${D[@]}" &&
        check "(a) dvgo render --path orbit ($VIDEO)" "${BN[@]}" render -w "$W" --model top2 --path orbit --frames 8 \
          --video "$W/orbit.$VIDEO" "${D[@]}"
    } &
    {
      check "(a) dvgo finetune top1" "${BN[@]}" finetune -w "$W-top1" --topk 1 "${D[@]}" &&
        check "(a) dvgo prune" "${BN[@]}" prune -w "$W-top1" --model top1 "${D[@]}" &&
        check "(a) dvgo eval pruned" "${BN[@]}" eval -w "$W-top1" --model top1-pruned "${D[@]}"
    } &
    {
      check "(a) dvgo finetune baseline" "${BN[@]}" finetune -w "$W-base" --baseline "${D[@]}"
      check "(a) dvgo finetune ensemble" "${BN[@]}" finetune -w "$W-base" --ensemble "${D[@]}" &&
        check "(a) dvgo eval (device auto)" "${BN[@]}" eval -w "$W-base" --report \
          --device "$([ "$DEV" = cuda ] && echo auto || echo cpu)" &&
        check "(a) dvgo count-params" "${BN[@]}" count-params -w "$W-base" "${D[@]}" &&
        check "(a) dvgo render --compare" "${BN[@]}" render -w "$W-base" --compare --views 1 "${D[@]}"
    } &
  fi
  wait
}

group_family() {  # group_family FAMILY: its experts, a Top-2 mixture, its eval
  local fam="$1" W="$TINY/ws-$1" D=(--device "$DEV")
  check "(a) $fam pretrain" "${BN[@]}" pretrain -w "$W" --data "$TINY/scene" --recipe "$TINY/$fam.yaml" "${D[@]}" &&
    check "(a) $fam build-moe" "${BN[@]}" build-moe -w "$W" "${D[@]}" &&
    check "(a) $fam finetune top2" "${BN[@]}" finetune -w "$W" --topk 2 "${D[@]}" &&
    check "(a) $fam eval" "${BN[@]}" eval -w "$W" --model top2 "${D[@]}"
}

group_torchrun() {
  if ! command -v torchrun >/dev/null; then
    skip_stage "(a) torchrun" "no torchrun on the PATH"
    return
  fi
  local W="$TINY/ws-torchrun"
  check "(a) torchrun pretrain (1 process)" torchrun --standalone --nproc-per-node 1 -m boostnerf_cli pretrain -w "$W" \
    --data "$TINY/scene" --recipe "$TINY/dvgo.yaml" --device "$DEV" &&
    check "(a) torchrun finetune (1 process)" bash -c "${BN[*]} build-moe -w '$W' --device $DEV &&
      torchrun --standalone --nproc-per-node 1 -m boostnerf_cli finetune -w '$W' --topk 1 --device $DEV"
}

group_quickstart() {
  if [ "$VIDEO" != mp4 ]; then  # its orbit video is an MP4, which needs the ffmpeg of imageio-ffmpeg
    skip_stage "(a) quickstart.sh" "imageio-ffmpeg (a dependency of boostnerf) is not installed here, and \
recipes/quickstart.sh writes an MP4: pip install imageio-ffmpeg to run it (its stages all run in the groups above)"
    return
  fi
  check "(a) quickstart.sh" env DEVICE="$DEV" PATH="$PATH" \
    bash -c "cd '$TINY' && bash '$HERE/recipes/quickstart.sh' ws-quickstart"
}

part_a() {
  renice -n 5 -p "$BASHPID" >/dev/null 2>&1  # below part (b), whose chain is the longest
  check "(a) make-scene" "${BN[@]}" make-scene "$TINY/scene" --size 48 --train-views 16 --test-views 4 || return
  local fam
  for fam in dvgo tensorf ngp; do
    "$PY" "$G" recipe gpu-check-a "$SCALE" "part-a:$fam" "$TINY/$fam.yaml" >/dev/null || return
  done
  group_dvgo &
  group_family tensorf &
  group_family ngp &
  check "(a) bench (two rows)" "${BN[@]}" bench -w "$TINY/bench" --data "$TINY/scene" --recipe "$TINY/dvgo.yaml" \
    --only dvgo-16,top1 --views 2 --device "$DEV" &
  group_torchrun &
  group_quickstart &
  wait
}

# ---- (b) the 400 px chain on SCENE ----------------------------------------------------------------------------------
part_b() {
  local B="$OUT/b" R="$OUT/b-recipe.yaml" res W m pids=() D=(--device "$DEV")
  mkdir -p "$B"
  read -r -a res < <("$PY" "$G" recipe gpu-check-b "$SCALE" "$HERE/recipes/blender-dvgo-paper-gpucheck.yaml" "$R")
  W="$B/ws"
  pretrain_experts "(b)" "$W" "$R" "$SCENE" dvgo "${res[@]}" || return
  local models=() r
  for r in "${res[@]}"; do models+=(--model "dvgo-$r=$W"); done
  # the partition oracle reads the three experts (each trained alone) and nothing else: it runs beside the rest
  # shellcheck disable=SC2086
  oracle_stage "(b) partition oracle" "$OUT/partition-oracle.json" "${models[@]}" $ORACLE_ARGS &
  pids+=($!)
  if check "(b) build-moe" "${BN[@]}" build-moe -w "$W" --recipe "$R" "${D[@]}"; then
    for m in top1 top2 ens experts; do copy_ws "$W" "$W-$m"; done
    {  # the experts' held-out table, beside the finetunes
      local names=()
      for r in "${res[@]}"; do names+=(--model "dvgo-$r"); done
      check "(b) eval experts" "${BN[@]}" eval -w "$W-experts" "${names[@]}" --no-costs --report "${D[@]}" &&
        check "(b) count-params experts" "${BN[@]}" count-params -w "$W-experts" "${names[@]}" --views "$COST_VIEWS" \
          "${D[@]}"
    } &
    pids+=($!)
    local ws flag
    for m in baseline top1 top2 ens; do
      ws="$W-$m"
      case $m in
        baseline) ws="$W"; flag=(--baseline) ;;  # the baseline trains in the workspace itself
        ens) flag=(--ensemble) ;;
        *) flag=(--topk "${m#top}") ;;
      esac
      {
        check "(b) finetune $m" "${BN[@]}" finetune -w "$ws" --recipe "$R" "${flag[@]}" "${D[@]}" &&
          check "(b) eval $m" "${BN[@]}" eval -w "$ws" --model "$m" --no-costs --report "${D[@]}" &&
          check "(b) count-params $m" "${BN[@]}" count-params -w "$ws" --model "$m" --views "$COST_VIEWS" "${D[@]}"
      } &
      pids+=($!)
    done
  fi
  for r in "${pids[@]}"; do wait "$r"; done
  {
    "$PY" "$G" device "$DEV"
    echo "scene $SCENE at $(grep -m1 image_size "$R" | tr -d ' '), recipe $R" \
      "(recipes/blender-dvgo-paper-gpucheck.yaml" \
      "with scripts/gpucheck.py's $SCALE settings); stages run concurrently (OUT/stages.md)"
    echo
  } >"$OUT/gpu-check.md"
  local rows=() i=0
  for r in "${res[@]}"; do
    local stage="(b) pretrain dvgo-$r"
    [ $i = 0 ] && stage="(b) pretrain geometry + dvgo-$r"
    rows+=(--model "dvgo-$r" "$W-experts" "$stage")
    i=$((i + 1))
  done
  rows+=(--model baseline "$W" "(b) finetune baseline")
  for m in top1 top2 ens; do rows+=(--model "$m" "$W-$m" "(b) finetune $m"); done
  "$PY" "$G" models "$OUT/gpu-check.md" --out "$OUT" --recipe "$R" --cost-views "$COST_VIEWS" "${rows[@]}" \
    >/dev/null || echo "gpu-check: the held-out table could not be written" >&2
  [ -f "$OUT/partition-oracle.json" ] && "$PY" "$G" table "$OUT/partition-oracle.json" "$OUT/gpu-check.md" \
    "Partitions of the experts on held-out views (research/partition_oracle.py)" >/dev/null
}

group_profile() {  # step_profile.py: operators, syncs and milliseconds per step of each kind, compiled
  if [ "${PROFILE:-$([ "$DEV" = cuda ] && echo 1 || echo 0)}" != 1 ]; then
    skip_stage "step_profile.py" "PROFILE=0 (on by default with CUDA only)"
    return
  fi
  renice -n 10 -p "$BASHPID" >/dev/null 2>&1  # the least urgent: a table if it fits the time
  # shellcheck disable=SC2086
  check "step_profile.py" "$PY" "$HERE/scripts/step_profile.py" --device "$DEV" $PROFILE_ARGS --workdir "$OUT/profile" \
    --table "$OUT/step-profile.json"
}

VIDEO=$("$PY" -c "import imageio_ffmpeg" 2>/dev/null && echo mp4 || echo gif)
PARTS="${PARTS:-$([ "${QUICK:-0}" = 1 ] && echo a || echo "a b")}"
pids=()
if [[ " $PARTS " == *" b "* ]]; then
  part_b &
  pids+=($!)
  group_profile &
  pids+=($!)
fi
if [[ " $PARTS " == *" a "* ]]; then
  part_a &
  pids+=($!)
fi
for p in "${pids[@]}"; do wait "$p"; done
if [ -f "$OUT/gpu-check.md" ]; then
  [ -f "$OUT/step-profile.json" ] && "$PY" "$G" table "$OUT/step-profile.json" "$OUT/gpu-check.md" \
    "One training step and one render chunk per kind (scripts/step_profile.py $PROFILE_ARGS)" >/dev/null
  echo
  cat "$OUT/gpu-check.md"
fi
gc_finish "$([ -f "$OUT/gpu-check.md" ] && echo "tables in $OUT/gpu-check.md, stages in $OUT/stages.md")"
