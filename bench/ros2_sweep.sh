#!/usr/bin/env bash
# The live sweep (mat:40, mat:70, all) on the emulated cameras, then on the ROS 2 path (the
# pure-Python robot on rmw_zenoh keys into `aoi3d up --rig`, exp:60 on top), same scene; the
# results are docs/real-cameras.md's table (results/ros2_sweep_*.json). About 30 minutes.
#   bash bench/ros2_sweep.sh [--epoch]    (--epoch: the robot phase-locked to the pipeline)
#   ROS_ONLY=1 OUT=runs/ros2-free bash bench/ros2_sweep.sh    (the ROS 2 half alone)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
D=${DATASET:-data/turbine-rotor}
OUT=${OUT:-runs/ros2-sweep}
# the bench's ports from the one table (bench/ports.py, BENCH_BLOCKS["ros2_sweep"])
BLOCK=$($PY -c 'from bench.ports import BENCH_BLOCKS as B; b = B["ros2_sweep"]; print(b.offset, b.zenoh)')
OFF=${PORT_OFFSET:-${BLOCK% *}}; ZP=${ZENOH_PORT:-${BLOCK#* }}
mkdir -p "$OUT"
$PY -m aoi3d_cli scene generate --out "$D"
if [ -z "${ROS_ONLY:-}" ]; then  # ROS_ONLY=1: the ROS 2 half alone
  $PY -m aoi3d_cli live sweep --up --dataset "$D" --policies mat:40,mat:70,all --no-sim --json \
    --out "$OUT/emulated" --port-offset "$OFF" --zenoh-port "$ZP" > "$OUT/emulated.json"
fi
$PY -m aoi3d_cli ros2 publish "$D" --time-scale 0.1 --connect "tcp/127.0.0.1:$ZP" \
  --write-rig "$OUT/rig.yaml" --rig-only
$PY -m aoi3d_cli up --rig "$OUT/rig.yaml" --delay exp:60 --port-offset "$OFF" --zenoh-port "$ZP" \
  --run-id ros2-sweep --quiet > "$OUT/up.log" 2>&1 &
UP=$!
trap 'kill -TERM $UP 2>/dev/null; wait $UP 2>/dev/null || true' EXIT
for _ in $(seq 1 120); do
  curl -sf "http://127.0.0.1:$((8105 + OFF))/healthz" >/dev/null \
    && curl -sf "http://127.0.0.1:$((8101 + OFF))/healthz" >/dev/null && break
  sleep 1
done
EPOCH=()
if [ "${1:-}" = "--epoch" ]; then
  EPOCH=(--epoch-s "$(curl -s "http://127.0.0.1:$((8101 + OFF))/status" \
    | $PY -c "import json, sys; print(json.load(sys.stdin)['time']['epoch_s'])")")
fi
$PY -m aoi3d_cli ros2 publish "$D" --time-scale 0.1 --connect "tcp/127.0.0.1:$ZP" "${EPOCH[@]}" \
  > "$OUT/robot.log" 2>&1 &
ROBOT=$!
sleep 20
$PY -m aoi3d_cli live sweep --dataset "$D" --policies mat:40,mat:70,all --no-sim --json \
  --out "$OUT/ros2" --port-offset "$OFF" > "$OUT/ros2.json"
curl -s "http://127.0.0.1:$((8101 + OFF))/status" > "$OUT/ingest-status.json"
kill -TERM $ROBOT; wait $ROBOT || true
