#!/usr/bin/env bash
# Train Vid2Param for the pendulum, spring and collision systems from scratch, IN PARALLEL on one
# GPU (three processes), each with a wall-clock budget, then evaluate each on 100 test-split
# videos and copy the results to $OUT.
#
# Run from the repository root on the GPU machine (no install needed):
#     PYTHONPATH=. bash scripts/gpu_train_systems.sh                 # ~7 min per model, in parallel
#     PYTHONPATH=. bash scripts/gpu_train_systems.sh --max-minutes 0.3 --steps 3 --batch 4 \
#         --chunk 8 --val-n 8 --stage-n 8 --eval-n 8 --device cpu  # the CPU dry run
#
# Options: --max-minutes M (each run's budget, default 7), --systems "a b c", --device D
# (default auto), --threads N (data threads per run, default 4), --eval-n N (default 100),
# --stage-n N (std_scale's videos, default the preset's 300), --out DIR (default $OUT or
# runs/gpu_systems); --steps/--batch/--chunk/--val-n pass through to the training command.
# Per system it writes DIR/v2p_<system>.pt (+ .json card), DIR/v2p_<system>_test.json and
# DIR/train_<system>.log; 7 files reach $OUT (3 checkpoints, 3 test JSONs, and
# cards_and_logs.tar.gz with the 3 cards and 3 logs). A run that does not export (a crash) is
# reported and the others go on.
set -u
MAX_MIN=7
SYSTEMS="pendulum spring collision"
DEVICE=auto
THREADS=4
EVAL_N=100
STAGE_N=""
DEST="${OUT:-runs/gpu_systems}"
PASS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --max-minutes) MAX_MIN="$2"; shift 2 ;;
    --systems) SYSTEMS="$2"; shift 2 ;;
    --device) DEVICE="$2"; shift 2 ;;
    --threads) THREADS="$2"; shift 2 ;;
    --eval-n) EVAL_N="$2"; shift 2 ;;
    --stage-n) STAGE_N="$2"; shift 2 ;;
    --out) DEST="$2"; shift 2 ;;
    --steps|--batch|--chunk|--val-n|--val-every|--chunk-epochs) PASS+=("$1" "$2"); shift 2 ;;
    *) echo "gpu_train_systems: unknown option $1" >&2; exit 2 ;;
  esac
done
export PYTHONPATH="${PYTHONPATH:-.}"
WORK="${WORK_DIR:-runs/gpu_systems_work}"
mkdir -p "$WORK" "$DEST"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

STAGE_ARGS=()
if [ -n "$STAGE_N" ]; then STAGE_ARGS=(--stages "std_scale:n=$STAGE_N"); fi
pids=()
for s in $SYSTEMS; do
  rm -rf "$WORK/$s"
  OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS python3 -m methods.vid2param.train \
    --system "$s" --out "$WORK/$s" --export "$WORK/v2p_$s.pt" --export-on-stop \
    --max-minutes "$MAX_MIN" --time-schedule --device "$DEVICE" --threads "$THREADS" --no-resume \
    --no-progress "${STAGE_ARGS[@]}" "${PASS[@]}" > "$WORK/train_$s.log" 2>&1 &
  pids+=($!)
done
status=0
i=0
for s in $SYSTEMS; do
  if ! wait "${pids[$i]}"; then echo "training $s FAILED (log: $WORK/train_$s.log)"; status=1; fi
  tail -3 "$WORK/train_$s.log"
  i=$((i + 1))
done

# evaluation: 100 test-split videos per system, in parallel (CPU or GPU, as the training)
pids=()
for s in $SYSTEMS; do
  if [ -f "$WORK/v2p_$s.pt" ]; then
    OMP_NUM_THREADS=$THREADS python3 -m methods.vid2param.evaluate_system --system "$s" \
      --checkpoint "$WORK/v2p_$s.pt" --n "$EVAL_N" --device "$DEVICE" \
      --out "$WORK/v2p_${s}_test.json" >> "$WORK/train_$s.log" 2>&1 &
    pids+=($!)
  fi
done
for p in "${pids[@]}"; do wait "$p" || status=1; done

for s in $SYSTEMS; do
  for f in "$WORK/v2p_$s.pt" "$WORK/v2p_${s}_test.json"; do
    if [ -f "$f" ]; then cp "$f" "$DEST/"; fi
  done
  if [ -f "$WORK/v2p_${s}_test.json" ]; then cat "$WORK/v2p_${s}_test.json"; fi
done
(cd "$WORK" && tar czf - v2p_*[a-z].json train_*.log 2>/dev/null) > "$DEST/cards_and_logs.tar.gz"
ls -la "$DEST"
exit $status
