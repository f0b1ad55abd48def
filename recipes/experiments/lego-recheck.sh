#!/usr/bin/env bash
# Issue 17: the lego figures rechecked after a change to the geometry stage (every 8th view held out, 100 px):
# DVGO's chain (experts 64/72/80, the baseline and Top-2 of blender-dvgo-cpu.yaml) and the best expert of the
# other two families (TensoRF-96, NGP L = 10), each in its own workspace under OUT. One thread per process.
#
# Usage: bash recipes/experiments/lego-recheck.sh LEGO OUT [dvgo] [others]
set -euo pipefail
LEGO="$1" OUT="$2"
shift 2
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
export OMP_NUM_THREADS=1 DEVICE=cpu
for what in "$@"; do
  case $what in
    dvgo) MODELS="baseline top2" bash "$HERE/recipes/chain.sh" blender-dvgo-cpu "$LEGO" "$OUT/dvgo" ;;
    others)
      boostnerf pretrain -w "$OUT/tensorf-96" --data "$LEGO" --recipe "$HERE/recipes/blender-tensorf-cpu.yaml" --res 96 --device cpu
      boostnerf pretrain -w "$OUT/ngp-10" --data "$LEGO" --recipe "$HERE/recipes/blender-ngp-cpu.yaml" --res 10 --device cpu ;;
    *) echo "unknown step $what (dvgo, others)" >&2; exit 2 ;;
  esac
done
