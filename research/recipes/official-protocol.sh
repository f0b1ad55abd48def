#!/usr/bin/env bash
# Issue 18: the official code's training protocol at CPU size on lego (every 8th view held out, 100 px).
#
# Usage: bash research/recipes/official-protocol.sh DATA OUT [m3|m4|m5|ablation|raw|raw-m3|...|seed1|ens|ens-m3|...|ablation-budget|lamX|penalty-P|vd-official|vd-largest|vd-visible|seed1-vd-official|seed1-all-official|gate-outside|gate-inside|all-official|all-official-top2|wideX|noiseX|long-base|long-top1|seed1-mX|hires|seed1-hires|hires-base96|m3-alone|oracle-64|oracle-80|oracle-96|same-mlp|seed1-same-mlp|same-mlp-step64|same-mlp-tuned|same-mlp-step64-tuned|seed1-same-mlp-step64-tuned|ladder|below|seed1-below|below-step40|below-vd-official|seed1-below-vd-official|px200|px200-alone|paper|paper-m3|paper-m4|paper-m5|llff-m3|tensorf-m3|ngp-m3|tensorf-m3-ens|ngp-m3-ens|tensorf-m3-st|ngp-m3-st|tensorf-m3-fastgate|ngp-m3-fastgate|collect]...
#   DATA        the scene folder: lego's (../shared/data/lego) for every step but llff-m3, which takes fern's
#   m3, m4, m5  recipes/chain.sh with blender-dvgo-cpu-official.yaml (M = 3: experts 64/72/80) and its
#               M = 4 (64..88) / M = 5 (56..88) variants written here; models baseline, top1, top2 (or $MODELS)
#   paper       the paper's appendix table at CPU size, one workspace per M, nothing shared between them: paper-m3,
#               paper-m4, paper-m5 each pretrain m3's (m4's, m5's) experts, build the mixture and train the baseline,
#               Top-1 with the raw-probability weight (the official code's), Top-2 and the ensemble -> OUT/paper-mM
#               (run them one at a time for their seconds)
#   ablation    on m3's experts: the official recipe with one factor at a time set back to boostnerf's
#               default, 2000 joint steps, Top-1 (and the baseline once)
#               (last row: the official raw-probability Top-1 weight, finetune --no-renormalize)
#   raw         Top-1 with the raw-probability weight on each of m3, m4, m5's experts and moe/init
#               (5,000 joint steps) -> OUT/m3-raw, m4-raw, m5-raw (raw-m3 ...: one size)
#   seed1       M = 3 again with finetuning seed 1 (batches drawn differently), on m3's experts and moe/init:
#               the baseline, Top-1 with the straight-through and with the raw-probability weight
#               -> OUT/m3-base-s1, m3-st-s1, m3-raw-s1
#   ens         the ensemble (every expert on every sample, the paper's Ens column) on each of m3, m4, m5's
#               experts and moe/init (5,000 joint steps) -> OUT/m3-ens, m4-ens, m5-ens
#   ablation-budget  the budget factor of the ablation: the official recipe with 4,000-step experts (boostnerf's
#               default) and 2,000 joint steps, its own experts trained here; Top-1 (the straight-through weight, as
#               the other ablation rows) and the baseline (the largest expert, 4,000 + 2,000 steps) -> OUT/abl-budget
#   lamX        M = 3 Top-1 with the raw-probability weight at lambda X (lam1e-4, lam3e-4: the recipe's 1e-3 sends
#               half the samples to the smallest expert) on m3's experts and moe/init -> OUT/m3-raw-lamX
#   penalty-P   M = 3 Top-1 with the raw-probability weight and penalty P (linear, none, ...; official: the official
#               code's weights "1, 1.5, 2.23") on m3's experts and moe/init -> OUT/m3-raw-penalty-P
#   vd-official M = 3 Top-1 with the raw-probability weight and the official code's V_D (moe.vd_source: largest,
#               moe.vd_filter: visible) on m3's experts and moe/init -> OUT/m3-raw-vd-official
#   vd-largest, vd-visible  the same with one of the two: moe.vd_source: largest alone, moe.vd_filter: visible alone
#               -> OUT/m3-raw-vd-largest, m3-raw-vd-visible
#   seed1-vd-official, seed1-all-official  vd-official and all-official with finetuning seed 1
#               -> OUT/m3-raw-vd-official-s1, m3-raw-all-official-s1
#   gate-outside, gate-inside  M = 3 with experts 72/80/88 (m4's, and its moe recipe), Top-1 with the raw-probability
#               weight: gate-outside copies the gate's grid from dvgo-64, left out of the mixture (the official code's
#               layout: its 128^3 gate model is not an expert), gate-inside from dvgo-72, the mixture's smallest
#               (boostnerf's) -> OUT/m3-88-gate64, m3-88-gate72 (baseline: m4's, dvgo-88)
#   all-official, all-official-top2  M = 3 Top-1 (raw weight) / Top-2 with both (the official V_D and penalty weights)
#               on m3's experts and moe/init -> OUT/m3-raw-all-official, m3-top2-all-official
#   long-base, long-top1  M = 3's baseline, and Top-1 with the raw weight and a 0.3 wide start, trained for $LONG
#               (10,000) joint steps instead of 5,000, on m3's experts and moe/init -> OUT/m3-long-base, m3-long-top1
#   wideX       M = 3 Top-1 with the raw-probability weight whose first X of the joint steps route to two experts
#               (finetune --wide-start X; not in the paper) on m3's experts and moe/init -> OUT/m3-raw-wideX
#   noiseX      M = 3 Top-1 with the raw-probability weight whose training chooses experts by noisy top-k, noise X
#               (finetune --gate-noise X; not in the paper) on m3's experts and moe/init -> OUT/m3-raw-noiseX
#   seed1-m3, seed1-m4, seed1-m5  that size again with finetuning seed 1, on its experts and moe/init: the
#               baseline and Top-2 -> OUT/mX-base-s1, mX-top2-s1
#   hires       M = 3 with experts 96/112/128 (gate 96^3, a copy of the smallest): grids finer than the 100 px
#               views resolve, as the paper's 160^3..384^3 are at 800 px; the baseline, Top-2, and Top-1 with the
#               raw-probability weight -> OUT/hires
#   same-mlp    M = 3 with experts 64/72/80 that all have m3's largest colour MLP (2 x 128): the paper's and the official
#               code's experts differ only in their grids (docs/paper-map.md); the recipe widens the MLP with the grid
#               (64/96/128). Top-1 (raw weight), Top-2, then the baseline (dvgo-80, as m3's) -> OUT/m3-mlp128
#   seed1-same-mlp  same-mlp's Top-1 (raw weight) with finetuning seed 1 -> OUT/m3-mlp128-top1-s1
#   same-mlp-step64  same-mlp's experts, the mixture sampling at its smallest expert's step (moe.step_from: smallest;
#               the official code samples at the largest's), Top-1 with the raw weight -> OUT/m3-mlp128-step64
#   same-mlp-tuned, same-mlp-step64-tuned  Top-1 (raw weight) on same-mlp's (or same-mlp-step64's) experts and moe/init
#               with the two settings that raised Top-1 most in session 10, a 0.3 wide start and lambda 1e-4
#               -> OUT/m3-mlp128-tuned, m3-mlp128-step64-tuned (seed1-same-mlp-step64-tuned: the second with finetuning
#               seed 1, evaluated without costs -> OUT/m3-mlp128-step64-tuned-s1)
#   ladder      M = 3 with experts 50/64/80, 2 x 128 MLPs each: the paper's ladder (each expert about twice the
#               parameters of the one before, the same MLP) ending at m3's largest expert; the baseline is m3's
#               (dvgo-80), not retrained -> OUT/ladder (Top-1 raw weight, Top-2)
#   seed1-hires hires again with finetuning seed 1, on its experts and moe/init: the baseline and Top-1 (raw weight)
#               -> OUT/hires-base-s1, hires-top1-s1
#   px200       hires' experts (96/112/128) on 200 px views: the baseline (dvgo-128), Top-1 with the raw-probability
#               weight -> OUT/px200; px200-alone: its smaller experts dvgo-96 and dvgo-112 each alone for the baseline's
#               1,000 + 5,000 steps (two-expert recipes 88/96, 96/112) -> OUT/px200-alone96, px200-alone112
#   below       M = 3 with every expert below the resolution where one model stops improving at 100 px (80^3): experts
#               40/50/64, each with a 2 x 128 colour MLP (the paper's named ladder 160/200/256 in proportion, its experts'
#               equal MLPs, docs/paper-map.md); the baseline (dvgo-64) and Top-1 with the raw-probability weight -> OUT/below
#   seed1-below  below's baseline and Top-1 (raw weight) with finetuning seed 1 on its experts and moe/init, evaluated
#               without costs -> OUT/below-base-s1, below-top1-s1
#   below-step40  below's experts, the mixture sampling at its smallest expert's step (moe.step_from: smallest), Top-1
#               with the raw weight -> OUT/below-step40
#   below-vd-official  below's experts and moe/init, Top-1 with the raw weight and the official code's V_D (moe.vd_source:
#               largest, moe.vd_filter: visible: fewer samples reach the gate and the experts) -> OUT/below-raw-vd-official
#               (seed1-below-vd-official: with finetuning seed 1, evaluated without costs -> OUT/below-raw-vd-official-s1)
#   hires-base96  the control for hires: its smallest expert (dvgo-96) alone for 1,000 + 5,000 steps, as the baseline
#               of a two-expert recipe 88/96 -> OUT/hires-base96
#   m3-alone    the same control for m3: its smaller experts dvgo-64 and dvgo-72 each alone for 1,000 + 5,000 steps
#               (two-expert recipes 56/64 and 64/72) -> OUT/m3-alone64, m3-alone72
#   oracle-64, oracle-80, oracle-96  single models for research/partition_oracle.py: dvgo-64, dvgo-80 and dvgo-96,
#               each with a 2 x 128 colour MLP, alone for the baseline's 1,000 + 5,000 steps (two-expert recipes 56/64,
#               72/80, 88/96) -> OUT/oracle-64, OUT/oracle-80, OUT/oracle-96 (their `baseline`)
#   llff-m3     M = 3 away from lego: a LLFF forward-facing scene (fern, ../shared/data/fern, in NDC) at 252 px wide
#               (images_8 halved), m3's experts and the official recipe otherwise, 3,000 joint steps (a fern step
#               costs ~5x a lego one: ~120 samples per ray pass the occupancy grid, ~50 are coloured); the baseline (dvgo-80, 1,000 + 3,000
#               steps), Top-1 with the raw-probability weight, Top-2 and the ensemble -> OUT/llff-m3 (the paper's LLFF row is its
#               one where Top-1 is below its baseline at M = 3, with every family)
#   tensorf-m3, ngp-m3  M = 3 with the other families: blender-tensorf-cpu.yaml's experts (64/80/96) or
#               blender-ngp-cpu.yaml's (L = 6/8/10) and its gate (random: the official code has no TensoRF or
#               Instant-NGP mixture, and moe.gate_init: expert copies a dense grid), with the official protocol
#               otherwise: 1,000 pretraining steps, 5,000 joint steps at the family's pretraining rates decaying x0.1,
#               lambda 1e-3 over (sum c_i)^2 and visible samples, opacities mixed; the baseline, Top-1 with the
#               raw-probability weight and Top-2 (ENS=1: and the ensemble) -> OUT/tensorf-m3, OUT/ngp-m3
#   tensorf-m3-ens, ngp-m3-ens  the ensemble on tensorf-m3's (ngp-m3's) experts and moe/init -> OUT/tensorf-m3-ens ...
#   tensorf-m3-st, ngp-m3-st  Top-1 with boostnerf's straight-through weight (a chosen expert weighs 1) instead of the raw
#               probability, on tensorf-m3's (ngp-m3's) experts and moe/init -> OUT/tensorf-m3-st ...
#   tensorf-m3-fastgate, ngp-m3-fastgate  Top-1 with the raw-probability weight and the gate trained at the official
#               gate's rate (moe.lr_gate 0.1, ten times the family recipes'), on tensorf-m3's (ngp-m3's) experts and
#               moe/init -> OUT/tensorf-m3-fastgate ...
#   collect     copy every workspace's reports/eval.json into docs/data/ with training seconds, as
#               issue18-$TAG<workspace>.json (TAG empty by default)
# One thread per process (OMP_NUM_THREADS=1); run chains one at a time for timings.
set -euo pipefail
DATA="$1" OUT="$2"
shift 2
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
export OMP_NUM_THREADS=1 DEVICE=cpu
OFFICIAL="$HERE/recipes/blender-dvgo-cpu-official.yaml"
mkdir -p "$OUT"
experts_of() {  # experts_of SIZE W: a new workspace W holding the experts of OUT/SIZE (m3, m4, ...)
  mkdir -p "$2" && cp -r "$OUT/$1/experts" "$OUT/$1/manifest.json" "$2/"
}
from_size() {  # from_size SIZE W: a new workspace W holding SIZE's experts and its moe/init
  experts_of "$1" "$2" && mkdir -p "$2/moe" && cp "$OUT/$1/moe/init."* "$2/moe/"
}
raw_top1() {  # raw_top1 W FLAG...: M = 3 Top-1 with the raw-probability weight and FLAG... on m3's experts and moe/init
  # (recipe $RECIPE, by default the official one; $SIZE's experts and moe/init instead of m3's)
  local W="$1"
  shift
  from_size "${SIZE:-m3}" "$W"
  boostnerf finetune -w "$W" --recipe "${RECIPE:-$OFFICIAL}" --topk 1 --no-renormalize "$@" --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1
}
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
OFFICIAL_PENALTY="1, 1.5, 2.23"  # the official code's penalty weights for 3 experts (docs/paper-map.md)
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
gate_layout() {  # gate_layout SRC RES: M = 3 with m4's experts 72/80/88, the gate copied from SRC at gate_res RES,
  # Top-1 with the raw-probability weight -> OUT/m3-88-gateRES
  local W="$OUT/m3-88-gate$2" recipe
  recipe="$(variant "m4-gate$2" "64, 72, 80, 88" "64: 64, 72: 96, 80: 128, 88: 128" "$2")"
  recipe_with "$recipe" "$OUT/official-gate-$1.yaml" "moe.gate_from=$1" > /dev/null
  experts_of m4 "$W"
  boostnerf build-moe -w "$W" --recipe "$OUT/official-gate-$1.yaml" --experts dvgo-72,dvgo-80,dvgo-88 --device cpu
  boostnerf finetune -w "$W" --recipe "$OUT/official-gate-$1.yaml" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1
}
family_official() {  # family_official FAMILY: blender-FAMILY-cpu.yaml with the official protocol's budget and mixture
  # training (its gate kept); print the recipe's path
  local src="$HERE/recipes/blender-$1-cpu.yaml" lrs
  lrs="$(python -c 'import sys, yaml; t = yaml.safe_load(open(sys.argv[1]))["pretrain"]["train"]; print(t["lr_grid"], t["lr_mlp"])' "$src")"
  recipe_with "$src" "$OUT/official-$1-m3.yaml" pretrain.iters=1000 moe.iters=5000 moe.lam=0.001 moe.penalty=geometric \
    moe.aux_norm=counts moe.aux_samples=visible moe.mix=alpha \
    "moe.train={batch_rays: 1024, lr_grid: ${lrs% *}, lr_mlp: ${lrs#* }, lr_decay: 0.1, log_every: 250, checkpoint_every: 500}"
}
M4=("64, 72, 80, 88" "64: 64, 72: 96, 80: 128, 88: 128" 64)  # m4's experts: variant's RES HIDDEN GATE_RES
M5=("56, 64, 72, 80, 88" "56: 64, 64: 64, 72: 96, 80: 128, 88: 128" 56)  # m5's
HIRES=("96, 112, 128" "96: 64, 112: 96, 128: 128" 96)  # hires' experts: variant's RES HIDDEN GATE_RES
BELOW=("40, 50, 64" "40: 128, 50: 128, 64: 128" 40)  # below's: every expert under the 100 px plateau, 2 x 128 MLPs
MLP128=("64, 72, 80" "64: 128, 72: 128, 80: 128" 64)  # same-mlp's: m3's experts, each with a 2 x 128 colour MLP
experts_and_moe() {  # experts_and_moe W RECIPE: pretrain W's experts and build its mixture
  boostnerf pretrain -w "$1" --data "$DATA" --recipe "$2" --device cpu
  boostnerf build-moe -w "$1" --recipe "$2" --device cpu
}
prepare() {  # prepare W RECIPE: pretrain W's experts, build its mixture and train its baseline
  experts_and_moe "$@"
  boostnerf finetune -w "$1" --recipe "$2" --baseline --device cpu
}
mixtures() {  # mixtures W RECIPE: W's experts, moe/init, Top-1 with the raw-probability weight and Top-2 (ENS=1: and
  # the ensemble), and the baseline (first; BASELINE=last: after the mixtures; BASELINE=none: not trained, when
  # another workspace has it)
  local b="${BASELINE:-first}"
  if [ "$b" = first ]; then prepare "$@"; else experts_and_moe "$@"; fi
  boostnerf finetune -w "$1" --recipe "$2" --topk 1 --no-renormalize --device cpu
  boostnerf finetune -w "$1" --recipe "$2" --topk 2 --device cpu
  [ "${ENS:-0}" = 1 ] && boostnerf finetune -w "$1" --recipe "$2" --ensemble --device cpu
  [ "$b" = last ] && boostnerf finetune -w "$1" --recipe "$2" --baseline --device cpu
  boostnerf eval -w "$1" --report --device cpu
}
baseline_top1() {  # baseline_top1 W RECIPE: W's experts, moe/init and baseline, then Top-1 with the raw-probability
  # weight; every model evaluated
  prepare "$@"
  boostnerf finetune -w "$1" --recipe "$2" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$1" --report --device cpu
}
smallest_step() {  # smallest_step SIZE NAME RECIPE: SIZE's experts, a mixture that samples at its smallest expert's
  # step (RECIPE with moe.step_from: smallest, written to OUT/official-NAME.yaml), Top-1 with the raw-probability
  # weight -> OUT/NAME
  local W="$OUT/$2" recipe
  recipe="$(recipe_with "$3" "$OUT/official-$2.yaml" moe.step_from=smallest)"
  experts_of "$1" "$W"
  boostnerf build-moe -w "$W" --recipe "$recipe" --device cpu
  boostnerf finetune -w "$W" --recipe "$recipe" --topk 1 --no-renormalize --device cpu
  boostnerf eval -w "$W" --report --device cpu --model top1
}
alone() {  # alone NAME RES HIDDEN GATE_RES [KEY=VALUE...]: the larger of two experts alone for the baseline's steps
  # -> OUT/NAME
  prepare "$OUT/$1" "$(variant "$@")"
  boostnerf eval -w "$OUT/$1" --report --device cpu --model baseline
}
seed1_model() {  # seed1_model SIZE RECIPE V MODEL FLAG...: finetune MODEL (FLAG...) with finetuning seed 1 on
  # SIZE's experts and moe/init -> OUT/SIZE-V-s1, evaluated without costs
  local W="$OUT/$1-$3-s1" recipe="$2" model="$4"
  from_size "$1" "$W"
  shift 4
  boostnerf finetune -w "$W" --recipe "$recipe" "$@" --seed 1 --device cpu
  boostnerf eval -w "$W" --report --no-costs --device cpu --model "$model"
}
for what in "$@"; do
  case $what in
    m3) MODELS="${MODELS:-baseline top1 top2}" bash "$HERE/recipes/chain.sh" "$OFFICIAL" "$DATA" "$OUT/m3" ;;
    m4) MODELS="${MODELS:-baseline top1 top2}" bash "$HERE/recipes/chain.sh" "$(variant m4 "${M4[@]}")" "$DATA" "$OUT/m4" ;;
    m5) MODELS="${MODELS:-baseline top1 top2}" bash "$HERE/recipes/chain.sh" "$(variant m5 "${M5[@]}")" "$DATA" "$OUT/m5" ;;
    paper) for m in m3 m4 m5; do bash "${BASH_SOURCE[0]}" "$DATA" "$OUT" "paper-$m"; done ;;
    paper-m3) ENS=1 mixtures "$OUT/paper-m3" "$OFFICIAL" ;;
    paper-m4) ENS=1 mixtures "$OUT/paper-m4" "$(variant m4 "${M4[@]}")" ;;
    paper-m5) ENS=1 mixtures "$OUT/paper-m5" "$(variant m5 "${M5[@]}")" ;;
    llff-m3) ENS=1 mixtures "$OUT/llff-m3" "$(variant llff-m3 "64, 72, 80" "64: 64, 72: 96, 80: 128" 64 moe.iters=3000 \
      "data={image_size: 252, holdout_every: 8, format: llff}")" ;;
    tensorf-m3|ngp-m3) mixtures "$OUT/$what" "$(family_official "${what%-m3}")" ;;
    tensorf-m3-ens|ngp-m3-ens|tensorf-m3-st|ngp-m3-st|tensorf-m3-fastgate|ngp-m3-fastgate)
      model=ens flags=(--ensemble) recipe="$(family_official "${what%-m3-*}")"
      [ "${what##*-}" = st ] && model=top1 flags=(--topk 1)
      if [ "${what##*-}" = fastgate ]; then
        model=top1 flags=(--topk 1 --no-renormalize)
        recipe="$(recipe_with "$recipe" "$OUT/official-$what.yaml" moe.lr_gate=0.1)"
      fi
      from_size "${what%-*}" "$OUT/$what"
      boostnerf finetune -w "$OUT/$what" --recipe "$recipe" "${flags[@]}" --device cpu
      boostnerf eval -w "$OUT/$what" --report --device cpu --model $model ;;
    hires) mixtures "$OUT/hires" "$(variant hires "${HIRES[@]}")" ;;
    same-mlp) BASELINE=last mixtures "$OUT/m3-mlp128" "$(variant m3-mlp128 "${MLP128[@]}")" ;;
    seed1-same-mlp) seed1_model m3-mlp128 "$(variant m3-mlp128 "${MLP128[@]}")" top1 top1 \
      --topk 1 --no-renormalize ;;
    same-mlp-step64) smallest_step m3-mlp128 m3-mlp128-step64 "$(variant m3-mlp128 "${MLP128[@]}")" ;;
    same-mlp-tuned|same-mlp-step64-tuned|seed1-same-mlp-step64-tuned)
      base="${what#seed1-}" seed=() costs=()
      src="${base%-tuned}"; src="m3-mlp128${src#same-mlp}" W="$OUT/${base/same-mlp/m3-mlp128}"
      [ "$base" = "$what" ] || { seed=(--seed 1); costs=(--no-costs); W="$W-s1"; }
      recipe="$(variant m3-mlp128 "${MLP128[@]}")"
      [ "$src" = m3-mlp128 ] || recipe="$OUT/official-m3-mlp128-step64.yaml"  # written by same-mlp-step64
      from_size "$src" "$W"
      boostnerf finetune -w "$W" --recipe "$recipe" --topk 1 --no-renormalize --wide-start 0.3 --lambda 1e-4 \
        "${seed[@]}" --device cpu
      boostnerf eval -w "$W" --report "${costs[@]}" --device cpu --model top1 ;;
    ladder) BASELINE=none mixtures "$OUT/ladder" "$(variant ladder "50, 64, 80" "50: 128, 64: 128, 80: 128" 50)" ;;
    seed1-hires)
      recipe="$(variant hires "${HIRES[@]}")"
      seed1_model hires "$recipe" base baseline --baseline
      seed1_model hires "$recipe" top1 top1 --topk 1 --no-renormalize ;;
    px200) baseline_top1 "$OUT/px200" "$(variant px200 "${HIRES[@]}" data.image_size=200)" ;;
    below) baseline_top1 "$OUT/below" "$(variant below "${BELOW[@]}")" ;;
    seed1-below)
      recipe="$(variant below "${BELOW[@]}")"
      seed1_model below "$recipe" base baseline --baseline
      seed1_model below "$recipe" top1 top1 --topk 1 --no-renormalize ;;
    below-step40) smallest_step below below-step40 "$(variant below "${BELOW[@]}")" ;;
    below-vd-official|seed1-below-vd-official)
      recipe="$(variant below-vd-official "${BELOW[@]}" moe.vd_source=largest moe.vd_filter=visible)"
      if [ $what = below-vd-official ]; then
        SIZE=below RECIPE="$recipe" raw_top1 "$OUT/below-raw-vd-official"
      else
        seed1_model below "$recipe" raw-vd-official top1 --topk 1 --no-renormalize
      fi ;;
    px200-alone)
      alone px200-alone96 "88, 96" "88: 64, 96: 64" 88 data.image_size=200
      alone px200-alone112 "96, 112" "96: 64, 112: 96" 96 data.image_size=200 ;;
    hires-base96) alone hires-base96 "88, 96" "88: 64, 96: 64" 88 ;;
    oracle-64) alone oracle-64 "56, 64" "56: 128, 64: 128" 56 ;;
    oracle-80) alone oracle-80 "72, 80" "72: 128, 80: 128" 72 ;;
    oracle-96) alone oracle-96 "88, 96" "88: 128, 96: 128" 88 ;;
    m3-alone)
      alone m3-alone64 "56, 64" "56: 64, 64: 64" 56
      alone m3-alone72 "64, 72" "64: 64, 72: 96" 64 ;;
    ablation)
      python - "$OFFICIAL" "$OUT" <<'PY'
import copy, sys, yaml
base = yaml.safe_load(open(sys.argv[1])); base["moe"]["iters"] = 2000
variants = {"official": {},
            "gate-random": {"gate_init": "random", "gate_res": 24, "gate_channels": 8, "gate_layers": 2, "lr_gate": 0.01},
            "aux-batch-all": {"aux_norm": "batch", "aux_samples": "all"},
            "mix-density": {"mix": "density"},
            "rates-0.3x": {"train": {**base["moe"]["train"], "lr_grid": 0.03, "lr_mlp": 0.0005}}}
for name, change in variants.items():
    r = copy.deepcopy(base); r["moe"].update(change)
    yaml.safe_dump(r, open(f"{sys.argv[2]}/abl-{name}.yaml", "w"), sort_keys=False)
PY
      cp "$OUT/abl-official.yaml" "$OUT/abl-raw-prob.yaml"
      for v in official gate-random aux-batch-all mix-density rates-0.3x raw-prob; do
        W="$OUT/abl-$v"
        experts_of m3 "$W"
        boostnerf build-moe -w "$W" --recipe "$OUT/abl-$v.yaml" --device cpu
        weight=()
        [ $v = raw-prob ] && weight=(--no-renormalize)
        boostnerf finetune -w "$W" --recipe "$OUT/abl-$v.yaml" --topk 1 "${weight[@]}" --device cpu
        models=(--model top1)
        if [ $v = official ]; then
          boostnerf finetune -w "$W" --recipe "$OUT/abl-$v.yaml" --baseline --device cpu
          models+=(--model baseline)
        fi
        boostnerf eval -w "$W" --report --device cpu "${models[@]}"
      done ;;
    raw|raw-m3|raw-m4|raw-m5)
      sizes="m3 m4 m5"
      [ $what = raw ] || sizes="${what#raw-}"
      for m in $sizes; do
        recipe="$OUT/official-$m.yaml"
        [ $m = m3 ] && recipe="$OFFICIAL"
        W="$OUT/$m-raw"
        from_size $m "$W"
        boostnerf finetune -w "$W" --recipe "$recipe" --topk 1 --no-renormalize --device cpu
        boostnerf eval -w "$W" --report --device cpu --model top1
      done ;;
    seed1)
      seed1_model m3 "$OFFICIAL" base baseline --baseline
      seed1_model m3 "$OFFICIAL" st top1 --topk 1
      seed1_model m3 "$OFFICIAL" raw top1 --topk 1 --no-renormalize ;;
    ens|ens-m3|ens-m4|ens-m5)
      sizes="m3 m4 m5"
      [ $what = ens ] || sizes="${what#ens-}"
      for m in $sizes; do
        recipe="$OUT/official-$m.yaml"
        [ $m = m3 ] && recipe="$OFFICIAL"
        W="$OUT/$m-ens"
        from_size $m "$W"
        boostnerf finetune -w "$W" --recipe "$recipe" --ensemble --device cpu
        boostnerf eval -w "$W" --report --device cpu --model ens
      done ;;
    ablation-budget)
      W="$OUT/abl-budget"
      recipe_with "$OUT/abl-official.yaml" "$OUT/abl-budget.yaml" pretrain.iters=4000 > /dev/null
      boostnerf pretrain -w "$W" --data "$DATA" --recipe "$OUT/abl-budget.yaml" --device cpu
      boostnerf build-moe -w "$W" --recipe "$OUT/abl-budget.yaml" --device cpu
      boostnerf finetune -w "$W" --recipe "$OUT/abl-budget.yaml" --topk 1 --device cpu
      boostnerf finetune -w "$W" --recipe "$OUT/abl-budget.yaml" --baseline --device cpu
      boostnerf eval -w "$W" --report --device cpu --model top1 --model baseline ;;
    lam[0-9]*) raw_top1 "$OUT/m3-raw-$what" --lambda "${what#lam}" ;;
    penalty-official) raw_top1 "$OUT/m3-raw-$what" --penalty "$OFFICIAL_PENALTY" ;;
    penalty-*) raw_top1 "$OUT/m3-raw-$what" --penalty "${what#penalty-}" ;;
    vd-official) RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-$what" ;;
    vd-largest) RECIPE="$(official_vd largest opacity)" raw_top1 "$OUT/m3-raw-$what" ;;
    vd-visible) RECIPE="$(official_vd smallest visible)" raw_top1 "$OUT/m3-raw-$what" ;;
    seed1-vd-official) RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-vd-official-s1" --seed 1 ;;
    seed1-all-official) RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-all-official-s1" --penalty "$OFFICIAL_PENALTY" --seed 1 ;;
    gate-outside) gate_layout dvgo-64 64 ;;
    gate-inside) gate_layout dvgo-72 72 ;;
    all-official) RECIPE="$(official_vd)" raw_top1 "$OUT/m3-raw-$what" --penalty "$OFFICIAL_PENALTY" ;;
    all-official-top2)
      W="$OUT/m3-top2-all-official"
      from_size m3 "$W"
      boostnerf finetune -w "$W" --recipe "$(official_vd)" --topk 2 --penalty "$OFFICIAL_PENALTY" --device cpu
      boostnerf eval -w "$W" --report --device cpu --model top2 ;;
    long-base|long-top1)
      W="$OUT/m3-$what"
      from_size m3 "$W"
      if [ $what = long-base ]; then
        boostnerf finetune -w "$W" --recipe "$OFFICIAL" --baseline --iters "${LONG:-10000}" --device cpu; model=baseline
      else
        boostnerf finetune -w "$W" --recipe "$OFFICIAL" --topk 1 --no-renormalize --wide-start 0.3 \
          --iters "${LONG:-10000}" --device cpu; model=top1
      fi
      boostnerf eval -w "$W" --report --device cpu --model $model ;;
    wide[0-9]*) raw_top1 "$OUT/m3-raw-$what" --wide-start "${what#wide}" ;;
    noise[0-9]*) raw_top1 "$OUT/m3-raw-$what" --gate-noise "${what#noise}" ;;
    seed1-m3|seed1-m4|seed1-m5)
      m="${what#seed1-}"
      recipe="$OUT/official-$m.yaml"
      [ $m = m3 ] && recipe="$OFFICIAL"
      seed1_model $m "$recipe" base baseline --baseline
      seed1_model $m "$recipe" top2 top2 --topk 2 ;;
    collect)
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
    (data / f"issue18-{tag}{ws.name}.json").write_text(json.dumps(report, indent=2) + "\n")
    print("wrote", data / f"issue18-{tag}{ws.name}.json")
PY
      ;;
    *) echo "unknown step $what (m3, m4, m5, ablation, raw, seed1, ens, ens-m3, ens-m4, ens-m5, ablation-budget, lamX, penalty-P, vd-official, vd-largest, vd-visible, seed1-vd-official, seed1-all-official, gate-outside, gate-inside, all-official, all-official-top2, wideX, noiseX, long-base, long-top1, seed1-m3, seed1-m4, seed1-m5, hires, seed1-hires, hires-base96, m3-alone, oracle-64, oracle-80, oracle-96, same-mlp, seed1-same-mlp, same-mlp-step64, same-mlp-tuned, same-mlp-step64-tuned, seed1-same-mlp-step64-tuned, ladder, below, seed1-below, below-step40, below-vd-official, seed1-below-vd-official, px200, px200-alone, paper, paper-m3, paper-m4, paper-m5, llff-m3, tensorf-m3, ngp-m3, tensorf-m3-ens, ngp-m3-ens, tensorf-m3-st, ngp-m3-st, tensorf-m3-fastgate, ngp-m3-fastgate, collect)" >&2; exit 2 ;;
  esac
done
