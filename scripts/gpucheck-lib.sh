# What scripts/gpu-check.sh and scripts/paper-check.sh share (sourced, not run): the device check, the CPU thread
# limits, the utilisation sampler, one stage run under the call's time budget, experts pretrained concurrently, and
# the closing summary. The Python side (settings per scale, tables, plan, probe) is scripts/gpucheck.py.
#
# The sourcing script sets HERE (the checkout) and NAME (its name, for messages), calls gc_begin, sets OUT (its work
# folder) and BUDGET_S, then calls gc_start; stages run through `check`; gc_finish prints the summary and exits.

PY="${PYTHON:-python3}"
G="$HERE/scripts/gpucheck.py"
BN=("$PY" "$G" cli)  # `boostnerf`, with one line at exit saying how long torch.compile took in the process
export PYTHONPATH="$HERE${PYTHONPATH:+:$PYTHONPATH}"  # the checkout itself, installed or not
export PYTHONUNBUFFERED=1

gc_begin() {  # gc_begin MIN_ARGS HELP_END ARGS...: the usage (the script's header, lines 2 to HELP_END) when fewer
  # than MIN_ARGS arguments; DEV (DEVICE: cuda) and SCALE (full or tiny); the device check
  local min="$1" help_end="$2"
  shift 2
  if [ $# -lt "$min" ]; then
    sed -n "2,${help_end}p" "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
  fi
  DEV="${DEVICE:-cuda}"
  SCALE="${SCALE:-full}"
  case "$SCALE" in full|tiny) ;; *) echo "$NAME: SCALE=$SCALE: use full or tiny" >&2; exit 2 ;; esac
  gc_require_device
}

gc_abs() { echo "$(cd "$(dirname "$1")" 2>/dev/null && pwd)/$(basename "$1")"; }  # a path made absolute

gc_require_device() {  # at once, with one line, when torch sees no CUDA GPU (DEVICE=cpu runs on the CPU)
  if [ "$DEV" = cuda ] && ! "$PY" -c "import torch, sys; sys.exit(not torch.cuda.is_available())" 2>/dev/null; then
    echo "$NAME: torch sees no CUDA GPU here (torch.cuda.is_available() is False); run it on a machine with one, or" \
      "check the script itself with DEVICE=cpu SCALE=tiny" >&2
    exit 3
  fi
}

# Many stage processes share the machine's cores: each gets THREADS CPU threads (default: an eighth of the cores)
# and inductor COMPILE_THREADS compile workers (a quarter), so that a dozen processes starting together do not
# oversubscribe the CPU that feeds the one GPU.
CORES="$(OMP_NUM_THREADS='' nproc 2>/dev/null || echo 4)"  # nproc itself obeys OMP_NUM_THREADS
export OMP_NUM_THREADS="${THREADS:-$(( CORES / 8 > 0 ? CORES / 8 : 1 ))}"
export MKL_NUM_THREADS="$OMP_NUM_THREADS"
export TORCHINDUCTOR_COMPILE_THREADS="${COMPILE_THREADS:-$(( CORES / 4 > 0 ? CORES / 4 : 1 ))}"

gc_start() {  # the clock, the deadline and the sampler
  mkdir -p "$OUT/logs" "$OUT/.pids"
  rm -f "$OUT/.stop"
  : >"$OUT/stages.tsv"
  START="$EPOCHREALTIME"
  DEADLINE=$(( ${START%.*} + BUDGET_S ))
  UNIT=GPU
  if [ "$DEV" = cuda ] && command -v nvidia-smi >/dev/null; then
    $(command -v stdbuf >/dev/null && echo stdbuf -oL) nvidia-smi \
      --query-gpu=timestamp,index,utilization.gpu,memory.used --format=csv,noheader,nounits -lms 500 \
      >"$OUT/util.csv" 2>"$OUT/logs/nvidia-smi.log" &
  else  # DEVICE=cpu: the CPU's busy share stands in, through the same code
    UNIT=CPU
    "$PY" "$G" sample-cpu "$OUT/util.csv" 2>"$OUT/logs/sampler.log" &
  fi
  SAMPLER=$!
  trap gc_stop_all INT TERM
  trap 'kill "$SAMPLER" 2>/dev/null' EXIT
  echo "$NAME: $("$PY" "$G" device "$DEV"); $CORES cores, $OMP_NUM_THREADS CPU threads and" \
    "$TORCHINDUCTOR_COMPILE_THREADS compile workers a process; budget ${BUDGET_S} s"
}

gc_stop_all() {  # an interrupt: start no more stages, stop the running ones (each in its own process group), wait
  # for every group to record its stages, then the summary
  local f
  trap '' INT TERM  # once
  : >"$OUT/.stop"
  echo "$NAME: interrupted: stopping the stages that run" >&2
  for f in "$OUT"/.pids/*; do
    [ -e "$f" ] && kill -INT -- "-${f##*/}" 2>/dev/null
  done
  kill "$SAMPLER" 2>/dev/null
  wait
  gc_finish "interrupted: run the same command again to go on" incomplete
}

gc_slug() { local s="${1//[()]/}"; s="${s//[^A-Za-z0-9._-]/_}"; echo "${s//__/_}"; }

check() {  # check NAME COMMAND...: run it (until the budget's end at most), its output in OUT/logs/NAME.log; print
  # one line (OK / FAIL / CUT: stopped at the budget's end, with its `ready in` lines and compile time); status 0 if OK
  local name="$1"
  shift
  # in a background group: an interrupt is the main shell's to handle (gc_stop_all), so that this stage is recorded
  [ "$BASHPID" != "$$" ] && trap '' INT TERM
  local log
  log="$OUT/logs/$(gc_slug "$name").log"
  local t0="$EPOCHREALTIME" left=$(( DEADLINE - EPOCHSECONDS )) rc status
  if (( left < 5 )) || [ -e "$OUT/.stop" ]; then
    echo "not started: $([ -e "$OUT/.stop" ] && echo "interrupted" || echo "the budget of ${BUDGET_S} s was spent")" \
      >"$log"
    rc=124
  else
    timeout -s INT -k 30 "$left" "$@" >"$log" 2>&1 &
    local pid=$!
    : >"$OUT/.pids/$pid"
    wait "$pid"
    rc=$?
    rm -f "$OUT/.pids/$pid"
  fi
  case $rc in 0) status=OK ;; 124|137) status=CUT ;; *) status=FAIL ;; esac
  [ "$rc" != 0 ] && [ -e "$OUT/.stop" ] && status=CUT
  "$PY" "$G" stage "$OUT" "$name" "$status" "$t0" "$EPOCHREALTIME" "$log"
  return "$rc"
}

skip_stage() {  # skip_stage NAME REASON: a SKIP line (not a failure)
  local log
  log="$OUT/logs/$(gc_slug "$1").log"
  echo "$2" >"$log"
  "$PY" "$G" stage "$OUT" "$1" SKIP "$EPOCHREALTIME" "$EPOCHREALTIME" "$log"
}

link_new() {  # link_new FILE TARGET: a hard link (a copy across file systems), unless TARGET exists
  [ -e "$2" ] || ln "$1" "$2" 2>/dev/null || cp "$1" "$2"
}

copy_ws() {  # copy_ws WS COPY: the workspace as hard links (stages replace files, never write into them), once
  [ -e "$2" ] || cp -al "$1" "$2" 2>/dev/null || cp -a "$1" "$2"
}

# pretrain_experts LABEL WS RECIPE DATA MODEL RES...: the geometry and the first expert in WS; as soon as the geometry
# is written, each other expert in a workspace of its own (WS-RES, where the geometry and the decoded scene are hard
# links to WS's), all at once; then their files are linked into WS, which then holds every expert, as if one
# `pretrain` had trained them (same scene, geometry and settings: build-moe takes them). Rerun, each stage skips what
# is finished and resumes a checkpoint.
pretrain_experts() {
  local label="$1" ws="$2" recipe="$3" data="$4" model="$5"
  shift 5
  local first="$1" r pids=() rc=0
  shift
  mkdir -p "$ws"
  check "$label pretrain geometry + $model-$first" "${BN[@]}" pretrain -w "$ws" --data "$data" --recipe "$recipe" \
    --res "$first" --device "$DEV" &
  local p0=$!
  while [ ! -f "$ws/experts/geometry.safetensors" ] && kill -0 "$p0" 2>/dev/null; do sleep 0.5; done
  if [ ! -f "$ws/experts/geometry.safetensors" ]; then
    wait "$p0"
    return 1
  fi
  for r in "$@"; do
    mkdir -p "$ws-$r/experts" "$ws-$r/cache"
    link_new "$ws/experts/geometry.safetensors" "$ws-$r/experts/geometry.safetensors"
    [ -f "$ws/cache/scene.safetensors" ] && link_new "$ws/cache/scene.safetensors" "$ws-$r/cache/scene.safetensors"
    check "$label pretrain $model-$r" "${BN[@]}" pretrain -w "$ws-$r" --data "$data" --recipe "$recipe" --res "$r" \
      --device "$DEV" &
    pids+=($!)
  done
  wait "$p0" || rc=1
  for r in "${pids[@]}"; do wait "$r" || rc=1; done
  for r in "$@"; do
    for f in "$ws-$r/experts/$model-$r.safetensors" "$ws-$r/experts/$model-$r.json"; do
      [ -f "$f" ] && link_new "$f" "$ws/experts/${f##*/}"
    done
  done
  return $rc
}

oracle_stage() {  # oracle_stage NAME JSON MODEL_ARGS...: research/partition_oracle.py, its JSON written under another
  # name and renamed once whole (a file there is a finished oracle)
  local name="$1" json="$2"
  shift 2
  check "$name" bash -c 'out="$1"; shift; "$@" --out "$out.tmp" && mv "$out.tmp" "$out"' _ "$json" \
    "$PY" "$HERE/research/partition_oracle.py" "$@" --device "$DEV"
}

gc_finish() {  # gc_finish [MESSAGE [incomplete]]: the stage table with utilisation, the counts, the exit status
  # (non-zero on any failure or stage cut at the budget, or when the caller says its work is incomplete)
  kill "$SAMPLER" 2>/dev/null
  wait "$SAMPLER" 2>/dev/null
  echo
  "$PY" "$G" summary "$OUT" --start "$START" --unit "$UNIT" >/dev/null
  cat "$OUT/stages.md"
  local n_ok n_fail n_cut n_skip
  n_ok=$(cut -f2 "$OUT/stages.tsv" | grep -c '^OK$')
  n_fail=$(cut -f2 "$OUT/stages.tsv" | grep -c '^FAIL$')
  n_cut=$(cut -f2 "$OUT/stages.tsv" | grep -c '^CUT$')
  n_skip=$(cut -f2 "$OUT/stages.tsv" | grep -c '^SKIP$')
  echo
  echo "$NAME: $n_ok OK, $n_fail FAIL, $n_cut cut (budget spent or interrupted), $n_skip skipped;" \
    "$(( EPOCHSECONDS - ${START%.*} )) s in all (budget ${BUDGET_S} s)${1:+; $1}"
  if (( n_fail + n_cut > 0 )) || [ "${2:-}" = incomplete ]; then
    exit 1
  fi
  exit 0
}
