#!/usr/bin/env bash
set -euo pipefail
export PYTHONPATH=/work/runs/rb OMP_NUM_THREADS=1
v=$1; W=/work/runs/rb/$v
boostnerf pretrain -w $W --data /work/shared/data/fern --recipe /work/runs/rb/$v.yaml --device cpu
boostnerf finetune -w $W --recipe /work/runs/rb/$v.yaml --baseline --device cpu
boostnerf eval -w $W --report --no-costs --device cpu
echo DONE
