#!/usr/bin/env bash
# The official code's training protocol at CPU size on lego (every 8th view held out, 100 px), and the questions
# docs/results.md asks of it. Each CASE trains and evaluates workspaces under OUT; the table of cases is
# run_case below, grouped by question, each with the docs/results.md table that records it (research/README.md).
#
# Usage: bash research/recipes/official-protocol.sh DATA OUT CASE...
#   DATA  the scene folder: lego's (data/nerf_synthetic/lego) for every case but llff-m3, which takes fern's
#   CASE  a case of run_case's table, run in the order given (an unknown one lists them all)
# Environment: MODELS (m3, m4, m5: the models recipes/chain.sh makes; default "baseline top1 top2"), ENS=1 (tensorf-m3,
# ngp-m3: also the ensemble), LONG (long-*: joint steps, default 10000), TAG (collect: the files' name prefix).
# Words: m3, m4, m5 are the official recipe (recipes/blender-dvgo-cpu-official.yaml, experts 64/72/80) and its
# M = 4 (64..88) and M = 5 (56..88) variants; "Top-1 raw" is Top-1 with the official code's raw-probability weight
# (finetune --topk 1 --no-renormalize); "on X's experts" starts a new workspace from a copy of OUT/X's experts and
# moe/init. One thread per process (OMP_NUM_THREADS=1); run one case at a time for its seconds.
set -euo pipefail
DATA="$1" OUT="$2"
shift 2
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
export OMP_NUM_THREADS=1 DEVICE=cpu
OFFICIAL="$HERE/recipes/blender-dvgo-cpu-official.yaml"
OFFICIAL_PENALTY="1, 1.5, 2.23"  # the official code's penalty weights for 3 experts (docs/paper-map.md)
mkdir -p "$OUT"

# ---- Recipes: each variant is the official recipe (or a family's CPU recipe) with named keys changed -------------
recipe_with() {  # recipe_with SRC DEST KEY=VALUE...: write recipe SRC with each dotted KEY (moe.gate_res,
  # pretrain.dvgo.hidden, ...) set to VALUE read as YAML ("[50, 64]", "{50: 128}", "largest") to DEST; print DEST
  python - "$@" <<'PY'
import sys, yaml
src, dest, *pairs = sys.argv[1:]
recipe = yaml.safe_load(open(src))
for pair in pairs:
    key, value = pair.split("=", 1)
    *sections, last = key.split(".")
    node = recipe
    for name in sections:
        if not isinstance(node.get(name), dict):
            sys.exit(f"recipe_with: {src} has no section {name} (in {key})")
        node = node[name]
    node[last] = yaml.safe_load(value)
yaml.safe_dump(recipe, open(dest, "w"), sort_keys=False)
PY
  echo "$2"
}
official_vd() {  # official_vd [SOURCE FILTER]: the official recipe with moe.vd_source SOURCE and moe.vd_filter FILTER,
  # by default the official code's V_D (the largest expert's density, and the visible filter)
  local source="${1:-largest}" filter="${2:-visible}"
  recipe_with "$OFFICIAL" "$OUT/official-vd-$source-$filter.yaml" "moe.vd_source=$source" "moe.vd_filter=$filter"
}
variant() {  # variant NAME RES HIDDEN GATE_RES [KEY=VALUE...]: the official recipe with other experts (and KEYs)
  local name="$1" res="$2" hidden="$3" gate="$4"
  shift 4
  recipe_with "$OFFICIAL" "$OUT/official-$name.yaml" "pretrain.res=[$res]" "pretrain.dvgo.hidden={$hidden}" \
    "moe.gate_res=$gate" "$@"
}
family_official() {  # family_official FAMILY: blender-FAMILY-cpu.yaml with the official protocol's budget and mixture
  # training (its gate kept); print the recipe's path
  local src="$HERE/recipes/blender-$1-cpu.yaml" lrs train
  lrs="$(python -c 'import sys, yaml; t = yaml.safe_load(open(sys.argv[1]))["pretrain"]["train"]
print(t["lr_grid"], t["lr_mlp"])' "$src")"  # the family's pretraining rates
  train="{batch_rays: 1024, lr_grid: ${lrs% *}, lr_mlp: ${lrs#* }, lr_decay: 0.1"
  train+=", log_every: 250, checkpoint_every: 500}"
  recipe_with "$src" "$OUT/official-$1-m3.yaml" pretrain.iters=1000 moe.iters=5000 moe.lam=0.001 \
    moe.penalty=geometric moe.aux_norm=counts moe.aux_samples=visible moe.mix=alpha "moe.train=$train"
}
# Expert sets, as variant's RES HIDDEN GATE_RES
M4=("64, 72, 80, 88" "64: 64, 72: 96, 80: 128, 88: 128" 64)
M5=("56, 64, 72, 80, 88" "56: 64, 64: 64, 72: 96, 80: 128, 88: 128" 56)
HIRES=("96, 112, 128" "96: 64, 112: 96, 128: 128" 96)  # past the 100 px plateau (80^3)
BELOW=("40, 50, 64" "40: 128, 50: 128, 64: 128" 40)  # every expert under the plateau, 2 x 128 MLPs
MLP128=("64, 72, 80" "64: 128, 72: 128, 80: 128" 64)  # m3's experts, each with a 2 x 128 colour MLP
official() {  # official SIZE: the official recipe of m3, m4 or m5 (m4's and m5's written to OUT/official-mM.yaml)
  case $1 in
    m3) echo "$OFFICIAL" ;;
    m4) variant m4 "${M4[@]}" ;;
    m5) variant m5 "${M5[@]}" ;;
  esac
}
sizes() {  # sizes CASE: the sizes a case runs on: raw -> m3 m4 m5, raw-m4 -> m4
  if [ "${1#*-}" = "$1" ]; then echo m3 m4 m5; else echo "${1#*-}"; fi
}
TUNED=(--topk 1 --no-renormalize --wide-start 0.3 --lambda 1e-4)  # Top-1 raw with the two settings that raised it most

# ---- Workspaces and training ------------------------------------------------------------------------------------
experts_of() {  # experts_of SIZE W: a new workspace W holding the experts of OUT/SIZE (m3, m4, ...)
  mkdir -p "$2" && cp -r "$OUT/$1/experts" "$OUT/$1/manifest.json" "$2/"
}
from_size() {  # from_size SIZE W: a new workspace W holding SIZE's experts and its moe/init
  experts_of "$1" "$2" && mkdir -p "$2/moe" && cp "$OUT/$1/moe/init."* "$2/moe/"
}
chain() {  # chain SIZE RECIPE: recipes/chain.sh with RECIPE -> OUT/SIZE, the models $MODELS (baseline top1 top2)
  MODELS="${MODELS:-baseline top1 top2}" bash "$HERE/recipes/chain.sh" "$2" "$DATA" "$OUT/$1"
}
tune() {  # tune SIZE W RECIPE MODEL FLAG...: finetune MODEL (FLAG...) on SIZE's experts and moe/init -> W, and
  # evaluate it (NO_COSTS=1: without costs)
  local size="$1" W="$2" recipe="$3" model="$4"
  shift 4
  from_size "$size" "$W"  # finetune with the research switches (--wide-start, --gate-noise) patched in
  python "$HERE/research/wide_start_noise.py" finetune -w "$W" --recipe "$recipe" "$@" --device cpu
  boostnerf eval -w "$W" --report ${NO_COSTS:+--no-costs} --device cpu --model "$model"
}
raw_top1() {  # raw_top1 W FLAG...: Top-1 raw with FLAG... on $SIZE's (default m3) experts, recipe $RECIPE (default
  # the official one) -> W
  tune "${SIZE:-m3}" "$1" "${RECIPE:-$OFFICIAL}" top1 --topk 1 --no-renormalize "${@:2}"
}
seed1_model() {  # seed1_model SIZE RECIPE V MODEL FLAG...: tune with finetuning seed 1 -> OUT/SIZE-V-s1, no costs
  local size="$1" recipe="$2" W="$OUT/$1-$3-s1" model="$4"
  shift 4
  NO_COSTS=1 tune "$size" "$W" "$recipe" "$model" "$@" --seed 1
}
experts_and_moe() {  # experts_and_moe W RECIPE: pretrain W's experts and build its mixture
  boostnerf pretrain -w "$1" --data "$DATA" --recipe "$2" --device cpu
  boostnerf build-moe -w "$1" --recipe "$2" --device cpu
}
prepare() {  # prepare W RECIPE: pretrain W's experts, build its mixture and train its baseline
  experts_and_moe "$@"
  boostnerf finetune -w "$1" --recipe "$2" --baseline --device cpu
}
mixtures() {  # mixtures W RECIPE: W's experts, moe/init, Top-1 raw and Top-2 (ENS=1: and the ensemble), and the
  # baseline (first; BASELINE=last: after the mixtures; BASELINE=none: not trained, when another workspace has it)
  local b="${BASELINE:-first}"
  if [ "$b" = first ]; then prepare "$@"; else experts_and_moe "$@"; fi
  boostnerf finetune -w "$1" --recipe "$2" --topk 1 --no-renormalize --device cpu
  boostnerf finetune -w "$1" --recipe "$2" --topk 2 --device cpu
  [ "${ENS:-0}" = 1 ] && boostnerf finetune -w "$1" --recipe "$2" --ensemble --device cpu
  [ "$b" = last ] && boostnerf finetune -w "$1" --recipe "$2" --baseline --device cpu
  boostnerf eval -w "$1" --report --device cpu
}
baseline_top1() {  # baseline_top1 W RECIPE: W's experts, moe/init and baseline, then Top-1 raw; every model evaluated
  prepare "$@"
  boostnerf finetune -w "$1" --recipe "$2" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$1" --report --device cpu
}
alone() {  # alone NAME RES HIDDEN GATE_RES [KEY=VALUE...]: the larger of two experts alone for the baseline's steps
  # -> OUT/NAME
  prepare "$OUT/$1" "$(variant "$@")"
  boostnerf eval -w "$OUT/$1" --report --device cpu --model baseline
}
smallest_step() {  # smallest_step SIZE NAME RECIPE: SIZE's experts, a mixture that samples at its smallest expert's
  # step (RECIPE with moe.step_from: smallest, written to OUT/official-NAME.yaml), Top-1 raw -> OUT/NAME
  local W="$OUT/$2" recipe
  recipe="$(recipe_with "$3" "$OUT/official-$2.yaml" moe.step_from=smallest)"
  experts_of "$1" "$W"
  boostnerf build-moe -w "$W" --recipe "$recipe" --device cpu
  boostnerf finetune -w "$W" --recipe "$recipe" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1
}
gate_layout() {  # gate_layout SRC RES: M = 3 with m4's experts 72/80/88, the gate copied from SRC at gate_res RES,
  # Top-1 raw -> OUT/m3-88-gateRES
  local W="$OUT/m3-88-gate$2" recipe
  recipe="$(variant "m4-gate$2" "64, 72, 80, 88" "64: 64, 72: 96, 80: 128, 88: 128" "$2")"
  recipe_with "$recipe" "$OUT/official-gate-$1.yaml" "moe.gate_from=$1" > /dev/null
  experts_of m4 "$W"
  boostnerf build-moe -w "$W" --recipe "$OUT/official-gate-$1.yaml" --experts dvgo-72,dvgo-80,dvgo-88 --device cpu
  boostnerf finetune -w "$W" --recipe "$OUT/official-gate-$1.yaml" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1
}
ablation() {  # ablation: on m3's experts, 2,000 joint steps, the official recipe with one factor at a time set back to
  # boostnerf's default (OUT/abl-V.yaml), Top-1 on each (raw-prob: the raw weight), the official row's baseline
  local abl="$OUT/abl-official.yaml" v W weight models
  recipe_with "$OFFICIAL" "$abl" moe.iters=2000 > /dev/null
  recipe_with "$abl" "$OUT/abl-gate-random.yaml" moe.gate_init=random moe.gate_res=24 moe.gate_channels=8 \
    moe.gate_layers=2 moe.lr_gate=0.01 > /dev/null
  recipe_with "$abl" "$OUT/abl-aux-batch-all.yaml" moe.aux_norm=batch moe.aux_samples=all > /dev/null
  recipe_with "$abl" "$OUT/abl-mix-density.yaml" moe.mix=density > /dev/null
  recipe_with "$abl" "$OUT/abl-rates-0.3x.yaml" moe.train.lr_grid=0.03 moe.train.lr_mlp=0.0005 > /dev/null
  cp "$abl" "$OUT/abl-raw-prob.yaml"
  for v in official gate-random aux-batch-all mix-density rates-0.3x raw-prob; do
    W="$OUT/abl-$v" weight=() models=(--model top1)
    [ $v = raw-prob ] && weight=(--no-renormalize)
    experts_of m3 "$W"
    boostnerf build-moe -w "$W" --recipe "$OUT/abl-$v.yaml" --device cpu
    boostnerf finetune -w "$W" --recipe "$OUT/abl-$v.yaml" --topk 1 "${weight[@]}" --device cpu
    if [ $v = official ]; then
      boostnerf finetune -w "$W" --recipe "$OUT/abl-$v.yaml" --baseline --device cpu
      models+=(--model baseline)
    fi
    boostnerf eval -w "$W" --report --device cpu "${models[@]}"
  done
}
ablation_budget() {  # ablation_budget: the ablation's budget factor, 4,000-step experts of its own (boostnerf's
  # default); Top-1 (straight-through, as the other rows) and the baseline -> OUT/abl-budget
  local W="$OUT/abl-budget" recipe="$OUT/abl-budget.yaml"
  recipe_with "$OUT/abl-official.yaml" "$recipe" pretrain.iters=4000 > /dev/null
  experts_and_moe "$W" "$recipe"
  boostnerf finetune -w "$W" --recipe "$recipe" --topk 1 --device cpu
  boostnerf finetune -w "$W" --recipe "$recipe" --baseline --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1 --model baseline
}
collect() {  # collect: every workspace's reports/eval.json with training seconds -> docs/data/official-$TAG<ws>.json
  python - "$OUT" "$HERE/docs/data" "${TAG:-}" <<'PY'
import json, sys
from pathlib import Path
out, data, tag = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
for ws in sorted(p for p in out.iterdir() if (p / "reports" / "eval.json").exists()):
    report = json.loads((ws / "reports" / "eval.json").read_text())
    experts = {p.stem: json.loads(p.read_text()) for p in (ws / "experts").glob("*.json")}
    pre = sum(e["seconds"] for e in experts.values())
    largest = max(experts.values(), key=lambda e: e["res"])["seconds"] if experts else 0
    for m in report["models"]:
        f = ws / "moe" / f"{m['name']}.json"
        tuned = json.loads(f.read_text())["seconds"] if f.exists() else 0
        own = experts[m["name"]]["seconds"] if m["name"] in experts else (largest if m["name"] == "baseline" else pre)
        m["extra"] = {"train s": str(round(own + tuned))}
    (data / f"official-{tag}{ws.name}.json").write_text(json.dumps(report, indent=2) + "\n")
    print("wrote", data / f"official-{tag}{ws.name}.json")
PY
}

# ---- The cases ---------------------------------------------------------------------------------------------------
# One per line: `    NAME)  # what it trains -> where`. cases() reads the names from these lines.
run_case() {  # run_case CASE: train and evaluate one case
  local what="$1" m
  case $what in
    # The official protocol at M = 3 / 4 / 5 (tables official-paper-layout, official-second-seed)
    m3|m4|m5)  # recipes/chain.sh with that size's official recipe: the models $MODELS -> OUT/mM
      chain "$what" "$(official "$what")" ;;
    raw|raw-m3|raw-m4|raw-m5)  # Top-1 raw on mM's experts (raw: each size) -> OUT/mM-raw
      for m in $(sizes "$what"); do tune "$m" "$OUT/$m-raw" "$(official "$m")" top1 --topk 1 --no-renormalize; done ;;
    ens|ens-m3|ens-m4|ens-m5)  # the ensemble (the paper's Ens column) on mM's experts (ens: each size) -> OUT/mM-ens
      for m in $(sizes "$what"); do tune "$m" "$OUT/$m-ens" "$(official "$m")" ens --ensemble; done ;;
    seed1)  # m3 with finetuning seed 1: the baseline, Top-1 straight-through and raw -> OUT/m3-base-s1, -st-s1, -raw-s1
      seed1_model m3 "$OFFICIAL" base baseline --baseline
      seed1_model m3 "$OFFICIAL" st top1 --topk 1
      seed1_model m3 "$OFFICIAL" raw top1 --topk 1 --no-renormalize ;;
    seed1-m3|seed1-m4|seed1-m5)  # that size with finetuning seed 1: the baseline and Top-2 -> OUT/mM-base-s1, -top2-s1
      m="${what#seed1-}"
      seed1_model "$m" "$(official "$m")" base baseline --baseline
      seed1_model "$m" "$(official "$m")" top2 top2 --topk 2 ;;

    # The paper's appendix table at CPU size, on one commit (table official-paper-layout)
    paper)  # paper-m3, paper-m4, paper-m5, one after the other
      for m in m3 m4 m5; do run_case "paper-$m"; done ;;
    paper-m3|paper-m4|paper-m5)  # that size alone: experts, baseline, Top-1 raw, Top-2, ensemble -> OUT/paper-mM
      ENS=1 mixtures "$OUT/$what" "$(official "${what#paper-}")" ;;

    # Ablation, one official factor at a time set back to boostnerf's default (table official-ablation)
    ablation)  # on m3's experts, 2,000 joint steps: Top-1 per factor, and the official row's baseline -> OUT/abl-*
      ablation ;;
    ablation-budget)  # the budget factor (after ablation): 4,000-step experts, Top-1 and the baseline -> OUT/abl-budget
      ablation_budget ;;

    # What sets Top-1's partition: its loss, its start, noisy top-k, a longer run (table official-top1-loss)
    lam[0-9]*)  # Top-1 raw at lambda X (lam1e-4, lam0) on m3's experts -> OUT/m3-raw-lamX
      raw_top1 "$OUT/m3-raw-$what" --lambda "${what#lam}" ;;
    penalty-official)  # Top-1 raw with the official penalty weights on m3's experts -> OUT/m3-raw-penalty-official
      raw_top1 "$OUT/m3-raw-$what" --penalty "$OFFICIAL_PENALTY" ;;
    penalty-*)  # Top-1 raw with penalty P (linear, none, ...) on m3's experts -> OUT/m3-raw-penalty-P
      raw_top1 "$OUT/m3-raw-$what" --penalty "${what#penalty-}" ;;
    wide[0-9]*)  # Top-1 raw whose first X of the joint steps route to two experts (--wide-start X) -> OUT/m3-raw-wideX
      raw_top1 "$OUT/m3-raw-$what" --wide-start "${what#wide}" ;;
    noise[0-9]*)  # Top-1 raw trained with noisy top-k, noise X (--gate-noise X) -> OUT/m3-raw-noiseX
      raw_top1 "$OUT/m3-raw-$what" --gate-noise "${what#noise}" ;;
    long-base)  # m3's baseline for $LONG joint steps instead of 5,000 -> OUT/m3-long-base
      tune m3 "$OUT/m3-$what" "$OFFICIAL" baseline --baseline --iters "${LONG:-10000}" ;;
    long-top1)  # Top-1 raw with a 0.3 wide start for $LONG joint steps -> OUT/m3-long-top1
      tune m3 "$OUT/m3-$what" "$OFFICIAL" top1 --topk 1 --no-renormalize --wide-start 0.3 --iters "${LONG:-10000}" ;;

    # The official code's last choices: V_D, penalty weights, gate layout (official-top1-levers, official-second-seed)
    vd-official)  # Top-1 raw with the official V_D (vd_source largest, vd_filter visible) -> OUT/m3-raw-vd-official
      RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-$what" ;;
    vd-largest)  # the same with moe.vd_source: largest alone -> OUT/m3-raw-vd-largest
      RECIPE="$(official_vd largest opacity)" raw_top1 "$OUT/m3-raw-$what" ;;
    vd-visible)  # the same with moe.vd_filter: visible alone -> OUT/m3-raw-vd-visible
      RECIPE="$(official_vd smallest visible)" raw_top1 "$OUT/m3-raw-$what" ;;
    all-official)  # Top-1 raw with the official V_D and penalty weights -> OUT/m3-raw-all-official
      RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-$what" --penalty "$OFFICIAL_PENALTY" ;;
    all-official-top2)  # Top-2 with both -> OUT/m3-top2-all-official
      tune m3 "$OUT/m3-top2-all-official" "$(official_vd)" top2 --topk 2 --penalty "$OFFICIAL_PENALTY" ;;
    seed1-vd-official)  # vd-official with finetuning seed 1 -> OUT/m3-raw-vd-official-s1
      RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-vd-official-s1" --seed 1 ;;
    seed1-all-official)  # all-official with finetuning seed 1 -> OUT/m3-raw-all-official-s1
      RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-all-official-s1" --penalty "$OFFICIAL_PENALTY" --seed 1 ;;
    gate-outside)  # Top-1 raw on m4's 72/80/88, the gate copied from dvgo-64, left out (official) -> OUT/m3-88-gate64
      gate_layout dvgo-64 64 ;;
    gate-inside)  # the same with the gate copied from dvgo-72, the mixture's smallest (boostnerf's) -> OUT/m3-88-gate72
      gate_layout dvgo-72 72 ;;

    # Experts past the 100 px plateau, single models trained alone (official-top1-levers, official-second-seed)
    hires)  # experts 96/112/128 (gate 96^3): the baseline, Top-1 raw and Top-2 -> OUT/hires
      mixtures "$OUT/hires" "$(variant hires "${HIRES[@]}")" ;;
    seed1-hires)  # hires with finetuning seed 1: the baseline and Top-1 raw -> OUT/hires-base-s1, hires-top1-s1
      seed1_model hires "$(variant hires "${HIRES[@]}")" base baseline --baseline
      seed1_model hires "$(variant hires "${HIRES[@]}")" top1 top1 --topk 1 --no-renormalize ;;
    hires-base96)  # hires' smallest expert alone for the baseline's 1,000 + 5,000 steps -> OUT/hires-base96
      alone hires-base96 "88, 96" "88: 64, 96: 64" 88 ;;
    m3-alone)  # m3's smaller experts each alone for the baseline's steps -> OUT/m3-alone64, m3-alone72
      alone m3-alone64 "56, 64" "56: 64, 64: 64" 56
      alone m3-alone72 "64, 72" "64: 64, 72: 96" 64 ;;

    # Every expert's colour MLP 2 x 128, as the official code's (official-top1-levers, official-second-seed)
    same-mlp)  # m3's experts with 2 x 128 MLPs: Top-1 raw, Top-2, then the baseline -> OUT/m3-mlp128
      BASELINE=last mixtures "$OUT/m3-mlp128" "$(variant m3-mlp128 "${MLP128[@]}")" ;;
    seed1-same-mlp)  # same-mlp's Top-1 raw with finetuning seed 1 -> OUT/m3-mlp128-top1-s1
      seed1_model m3-mlp128 "$(variant m3-mlp128 "${MLP128[@]}")" top1 top1 --topk 1 --no-renormalize ;;
    same-mlp-step64)  # same-mlp's experts, sampled at the smallest expert's step, Top-1 raw -> OUT/m3-mlp128-step64
      smallest_step m3-mlp128 m3-mlp128-step64 "$(variant m3-mlp128 "${MLP128[@]}")" ;;
    same-mlp-tuned)  # Top-1 raw on same-mlp's experts, 0.3 wide start and lambda 1e-4 -> OUT/m3-mlp128-tuned
      tune m3-mlp128 "$OUT/m3-mlp128-tuned" "$(variant m3-mlp128 "${MLP128[@]}")" top1 "${TUNED[@]}" ;;
    same-mlp-step64-tuned)  # the same on same-mlp-step64's (after it) -> OUT/m3-mlp128-step64-tuned
      tune m3-mlp128-step64 "$OUT/m3-mlp128-step64-tuned" "$OUT/official-m3-mlp128-step64.yaml" top1 "${TUNED[@]}" ;;
    seed1-same-mlp-step64-tuned)  # that with finetuning seed 1 -> OUT/m3-mlp128-step64-tuned-s1
      seed1_model m3-mlp128-step64 "$OUT/official-m3-mlp128-step64.yaml" tuned top1 "${TUNED[@]}" ;;
    ladder)  # experts 50/64/80, 2 x 128 MLPs (the paper's ladder), m3's baseline: Top-1 raw, Top-2 -> OUT/ladder
      BASELINE=none mixtures "$OUT/ladder" "$(variant ladder "50, 64, 80" "50: 128, 64: 128, 80: 128" 50)" ;;

    # Two more regimes: every expert below the plateau, larger views (tables official-top1-levers, official-second-seed)
    below)  # experts 40/50/64, 2 x 128 MLPs: the baseline (dvgo-64) and Top-1 raw -> OUT/below
      baseline_top1 "$OUT/below" "$(variant below "${BELOW[@]}")" ;;
    seed1-below)  # below with finetuning seed 1: the baseline and Top-1 raw -> OUT/below-base-s1, below-top1-s1
      seed1_model below "$(variant below "${BELOW[@]}")" base baseline --baseline
      seed1_model below "$(variant below "${BELOW[@]}")" top1 top1 --topk 1 --no-renormalize ;;
    below-step40)  # below's experts, sampled at the smallest expert's step, Top-1 raw -> OUT/below-step40
      smallest_step below below-step40 "$(variant below "${BELOW[@]}")" ;;
    below-vd-official)  # Top-1 raw on below's experts with the official V_D -> OUT/below-raw-vd-official
      SIZE=below RECIPE="$(variant below-vd-official "${BELOW[@]}" moe.vd_source=largest moe.vd_filter=visible)" \
        raw_top1 "$OUT/below-raw-vd-official" ;;
    seed1-below-vd-official)  # that with finetuning seed 1 -> OUT/below-raw-vd-official-s1
      seed1_model below "$(variant below-vd-official "${BELOW[@]}" moe.vd_source=largest moe.vd_filter=visible)" \
        raw-vd-official top1 --topk 1 --no-renormalize ;;
    px200)  # hires' experts on 200 px views: the baseline (dvgo-128) and Top-1 raw -> OUT/px200
      baseline_top1 "$OUT/px200" "$(variant px200 "${HIRES[@]}" data.image_size=200)" ;;
    px200-alone)  # px200's smaller experts each alone for the baseline's steps -> OUT/px200-alone96, px200-alone112
      alone px200-alone96 "88, 96" "88: 64, 96: 64" 88 data.image_size=200
      alone px200-alone112 "96, 112" "96: 64, 112: 96" 96 data.image_size=200 ;;

    # Away from lego: fern (table official-fern)
    llff-m3)  # m3's experts on fern (252 px wide), 3,000 joint steps: baseline, Top-1 raw, Top-2, ens -> OUT/llff-m3
      ENS=1 mixtures "$OUT/llff-m3" "$(variant llff-m3 "64, 72, 80" "64: 64, 72: 96, 80: 128" 64 moe.iters=3000 \
        "data={image_size: 252, holdout_every: 8, format: llff}")" ;;

    # The other families under the official protocol (tables official-families, official-families-top1-weight)
    tensorf-m3|ngp-m3)  # the family's CPU experts and gate (random): baseline, Top-1 raw, Top-2 -> OUT/FAMILY-m3
      mixtures "$OUT/$what" "$(family_official "${what%-m3}")" ;;
    tensorf-m3-ens|ngp-m3-ens)  # the ensemble on FAMILY-m3's experts -> OUT/FAMILY-m3-ens
      tune "${what%-ens}" "$OUT/$what" "$(family_official "${what%-m3-ens}")" ens --ensemble ;;
    tensorf-m3-st|ngp-m3-st)  # Top-1 with the straight-through weight on FAMILY-m3's experts -> OUT/FAMILY-m3-st
      tune "${what%-st}" "$OUT/$what" "$(family_official "${what%-m3-st}")" top1 --topk 1 ;;
    tensorf-m3-fastgate|ngp-m3-fastgate)  # Top-1 raw, the gate at the official rate 0.1 -> OUT/FAMILY-m3-fastgate
      tune "${what%-fastgate}" "$OUT/$what" \
        "$(recipe_with "$(family_official "${what%-m3-fastgate}")" "$OUT/official-$what.yaml" moe.lr_gate=0.1)" \
        top1 --topk 1 --no-renormalize ;;

    # The ceiling of any partition of single models (tables results-oracle-*: research/partition_oracle.py)
    oracle-64)  # dvgo-64 with a 2 x 128 MLP alone for the baseline's steps -> OUT/oracle-64 (its `baseline`)
      alone oracle-64 "56, 64" "56: 128, 64: 128" 56 ;;
    oracle-80)  # dvgo-80 the same -> OUT/oracle-80
      alone oracle-80 "72, 80" "72: 128, 80: 128" 72 ;;
    oracle-96)  # dvgo-96 the same -> OUT/oracle-96
      alone oracle-96 "88, 96" "88: 128, 96: 128" 88 ;;

    # The tables' data
    collect)  # every workspace's reports/eval.json with training seconds -> docs/data/official-$TAG<workspace>.json
      collect ;;
    *)
      echo "unknown step $what ($(cases))" >&2
      exit 2 ;;
  esac
}
cases() {  # the case names of run_case's table, in its order (lamX for lam[0-9]*, penalty-P for penalty-*)
  sed -n 's/^    \([]a-z0-9|*[-]*\))  # .*/\1/p' "${BASH_SOURCE[0]}" | sed 's/\[0-9\]\*/X/; s/-\*$/-P/' \
    | paste -sd '|' | sed 's/|/, /g'
}
for what in "$@"; do
  run_case "$what"
done
