#!/usr/bin/env bash
# The one device call of the systems round: the three systems' Vid2Param models (in parallel,
# scripts/gpu_train_systems.sh) and the ball's 28x28 model from the one training command
# (TrainConfig() defaults and the preset's stages), all from scratch on one GPU with a
# wall-clock budget each. Results to $OUT: four checkpoints and one archive of cards, test
# JSONs and logs (the device returns at most 8 files).
set -u
MAX_MIN="${1:-5.5}"
export PYTHONPATH=.
mkdir -p runs/gpu_all
OMP_NUM_THREADS=3 python3 -m methods.vid2param.train --out runs/gpu_all/ball28 \
  --export runs/gpu_all/v2p_28x28_onecmd.pt --export-on-stop --max-minutes "$MAX_MIN" \
  --time-schedule --device auto --threads 3 --no-resume --no-progress \
  > runs/gpu_all/train_ball28.log 2>&1 &
ball=$!
WORK_DIR=runs/gpu_all bash scripts/gpu_train_systems.sh --max-minutes "$MAX_MIN" --threads 4 \
  --out runs/gpu_all/dest
wait $ball; echo "ball 28x28 exit $?"; tail -5 runs/gpu_all/train_ball28.log
cp runs/gpu_all/dest/v2p_*.pt runs/gpu_all/v2p_28x28_onecmd.pt "$OUT/" 2>/dev/null
(cd runs/gpu_all && tar czf "$OUT/results.tar.gz" dest/*.json dest/*.tar.gz v2p_28x28_onecmd.json \
  train_*.log ball28/*.json 2>/dev/null)
ls -la "$OUT"
