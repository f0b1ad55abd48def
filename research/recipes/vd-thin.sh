#!/usr/bin/env bash
# Does the mixture's density volume V_D cut thin structure? (docs/results.md, issue 17, "the density volume V_D
# keeps thin structure")
# The thin procedural scene at 80 px; DVGO (24/32/40) and Instant-NGP (L = 4/6) experts, Top-2 mixtures. Each model
# renders the held-out views with every skip on and with the empty-space skip off (V_D and occupancy), and
# research/thin_pixels.py scores the thin-structure pixels and the rest.
#   bash research/recipes/vd-thin.sh OUT
set -euo pipefail
OUT=${1:?usage: vd-thin.sh OUT}
HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
mkdir -p "$OUT"
[ -d "$OUT/thin" ] || boostnerf make-scene "$OUT/thin" --size 80 --train-views 28 --test-views 4 --content thin
for fam in dvgo ngp; do
  ws="$OUT/ws-$fam"
  boostnerf pretrain --data "$OUT/thin" --recipe "$HERE/thin-80px-$fam.yaml" -w "$ws" --device cpu
  boostnerf build-moe -w "$ws" --device cpu
  boostnerf finetune -w "$ws" --topk 2 --device cpu
  largest=$(python -c "import json, sys; print(json.load(open(sys.argv[1]))['moe']['init']['experts'][-1])" \
    "$ws/manifest.json")
  for model in "$largest" top2; do
    for skips in "" "--skip-off empty"; do
      # shellcheck disable=SC2086
      boostnerf render -w "$ws" --model "$model" $skips --device cpu > /dev/null
      echo "== $fam $model ${skips:-every skip on}"
      python "$ROOT/research/thin_pixels.py" "$OUT/thin" "$ws/renders/$model/test"
    done
  done
done
