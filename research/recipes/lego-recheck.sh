#!/usr/bin/env bash
# Issue 17: the lego figures, rechecked when the geometry stage changes (every 8th view held out, 100 px):
# each family's chain with its CPU recipe (experts, the baseline and Top-2: blender-{dvgo,tensorf,ngp}-cpu.yaml),
# each in its own workspace under OUT/FAMILY. One thread per process.
#
# Usage: bash research/recipes/lego-recheck.sh LEGO OUT [dvgo] [tensorf] [ngp]
set -euo pipefail
LEGO="$1" OUT="$2"
shift 2
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
export OMP_NUM_THREADS=1 DEVICE=cpu
for what in "$@"; do
  case $what in
    dvgo) MODELS="baseline top2" bash "$HERE/recipes/chain.sh" blender-dvgo-cpu "$LEGO" "$OUT/dvgo" ;;
    tensorf|ngp) MODELS="baseline top2" bash "$HERE/recipes/chain.sh" "blender-$what-cpu" "$LEGO" "$OUT/$what" ;;
    *) echo "unknown step $what (dvgo, tensorf, ngp)" >&2; exit 2 ;;
  esac
done
