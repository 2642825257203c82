#!/usr/bin/env bash
# Train Vid2Param for the pendulum, spring and collision systems from scratch, IN PARALLEL on one
# GPU (three processes), each with a wall-clock budget, then evaluate each on 100 test-split
# videos and copy the results to $OUT.
#
# Run from the repository root on the GPU machine (no install needed):
#     PYTHONPATH=. bash scripts/gpu_train_systems.sh                 # ~7 min per model, in parallel
#     PYTHONPATH=. bash scripts/gpu_train_systems.sh --max-minutes 0.3 --steps 3 --batch 4 \
#         --chunk 8 --nll-only-steps 3 --val-n 8 --stage-n 8 --eval-n 8 --device cpu  # the CPU dry run
#
# Options: --max-minutes M (each run's budget, default 7), --systems "a b c", --device D
# (default auto), --threads N (data threads per run, default 4), --eval-n N (default 100),
# --stage-n N (std_scale's videos, default the preset's 300), --out DIR (default $OUT or
# runs/gpu_systems); --steps/--batch/--chunk/--val-n pass through to the training command.
# Per system it writes DIR/v2p_<system>.pt (+ .json card), DIR/v2p_<system>_test.json and
# DIR/train_<system>.log, and the same for the warm-up's snapshot (v2p_<system>_warmup.*); 7 files
# reach $OUT (6 checkpoints and cards_and_logs.tar.gz with the cards, test JSONs and logs). A run that does not export (a crash) is
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
    --steps|--batch|--chunk|--val-n|--val-every|--chunk-epochs|--nll-only-steps) PASS+=("$1" "$2"); shift 2 ;;
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
    --export-warmup "$WORK/v2p_${s}_warmup.pt" \
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

# evaluation: 100 test-split videos per model (the final and the warm-up's), in parallel
pids=()
for s in $SYSTEMS; do
  for m in "$s" "${s}_warmup"; do
    if [ -f "$WORK/v2p_$m.pt" ]; then
      OMP_NUM_THREADS=2 python3 -m methods.vid2param.evaluate_system --system "$s" \
        --checkpoint "$WORK/v2p_$m.pt" --n "$EVAL_N" --device "$DEVICE" \
        --out "$WORK/v2p_${m}_test.json" >> "$WORK/train_$s.log" 2>&1 &
      pids+=($!)
    fi
  done
done
for p in "${pids[@]}"; do wait "$p" || status=1; done

# back: the checkpoints (at most 6) and one archive of cards, test JSONs and logs (7 files)
for s in $SYSTEMS; do
  for m in "$s" "${s}_warmup"; do
    if [ -f "$WORK/v2p_$m.pt" ]; then cp "$WORK/v2p_$m.pt" "$DEST/"; fi
    if [ -f "$WORK/v2p_${m}_test.json" ]; then
      python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], 'nMSE', {k: round(v, 4) for k, v in d['nmse_mean'].items()}, 'nMSE@200', {k: round(v, 4) for k, v in d['nmse']['200'].items()}, 'cov@200', d['coverage90']['200'])" "$WORK/v2p_${m}_test.json" "$m"
    fi
  done
done
(cd "$WORK" && tar czf - v2p_*.json train_*.log 2>/dev/null) > "$DEST/cards_and_logs.tar.gz"
ls -la "$DEST"
exit $status
