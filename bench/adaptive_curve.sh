#!/bin/sh
# The plug-in policy's Γ*(E[Y]) curve (aoi3d/policy/gamma_curve.json): the best MAT threshold
# against the mean delay of an exponential channel, at the adaptive study's budget (quick
# preset, 100 field steps per scored decision, no LPIPS), design seeds 100–101.
set -e
cd "$(dirname "$0")/.."
PYTHONPATH=. .venv/bin/python -m aoi3d_cli experiment delay --preset quick --steps-per-epoch 100 --no-lpips \
  --delays exp:10,exp:20,exp:40,exp:70,exp:100,exp:150,exp:200 --gammas 40,70,100,130,190,280 \
  --seeds 2 --seed-offset 100 --processes 2 --cache runs/adaptive-cache \
  --out results/adaptive-gamma-curve "$@"
