#!/usr/bin/env bash
# Second device call: continue the three systems' models from the first call's exports with the
# encoder's NLL alone (the warm-up that taught the ball's network g), in parallel, then evaluate.
set -u
MAX_MIN="${1:-4}"
INIT="${2:-runs/gpu_init}"
export PYTHONPATH=.
mkdir -p runs/g2
for s in pendulum spring collision; do
  OMP_NUM_THREADS=5 python3 -m methods.vid2param.train --system "$s" --out "runs/g2/$s" \
    --init "$INIT/v2p_$s.pt" --export "runs/g2/v2p_$s.pt" --export-on-stop \
    --max-minutes "$MAX_MIN" --time-schedule --device "${DEVICE:-auto}" --threads 5 --no-resume \
    --no-progress --steps 1500 --nll-only-steps 1500 ${EXTRA:-} > "runs/g2/train_$s.log" 2>&1 &
done
wait
for s in pendulum spring collision; do
  grep -E "val step|stopping" "runs/g2/train_$s.log" | tail -2
  [ -f "runs/g2/v2p_$s.pt" ] && OMP_NUM_THREADS=5 python3 -m methods.vid2param.evaluate_system \
    --system "$s" --checkpoint "runs/g2/v2p_$s.pt" --n "${EVAL_N:-100}" --device "${DEVICE:-auto}" \
    --out "runs/g2/v2p_${s}_test.json" >> "runs/g2/train_$s.log" 2>&1 &
done
wait
for s in pendulum spring collision; do
  python3 -c "import json; d=json.load(open('runs/g2/v2p_${s}_test.json')); print('$s', d['nmse_mean'], d['coverage90']['200'])"
done
cp runs/g2/v2p_*.pt "${OUT:-runs/g2}/" 2>/dev/null
(cd runs/g2 && tar czf "${OUT:-.}/results2.tar.gz" *.json train_*.log)
