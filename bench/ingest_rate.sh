#!/usr/bin/env bash
# How many real-time cameras the ingest takes: the pure-Python robot at time scale 1 (every
# camera a frame each 30 ms, raw rgb8 96×72) into `aoi3d up --rig`, for each camera count in
# CAMERAS; per run the robot's images sent, the ingest's frames published, its inbox drops and
# the lost samples (sequence gaps), and the median receipt − stamp. About 1.5 min per count.
#   bash bench/ingest_rate.sh            (CAMERAS="4 9 18" by default)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
D=${DATASET:-data/turbine-rotor}
OUT=${OUT:-runs/ingest-rate}
SECONDS_RUN=${SECONDS_RUN:-60}
BLOCK=$($PY -c 'from bench.ports import BENCH_BLOCKS as B; b = B["ros2_sweep"]; print(b.offset, b.zenoh)')
OFF=${PORT_OFFSET:-${BLOCK% *}}; ZP=${ZENOH_PORT:-${BLOCK#* }}
mkdir -p "$OUT"
$PY -m aoi3d_cli scene generate --out "$D"
for n in ${CAMERAS:-4 9 18}; do
  $PY -m aoi3d_cli ros2 publish "$D" --cameras "$n" --time-scale 1 --connect "tcp/127.0.0.1:$ZP" \
    --write-rig "$OUT/rig-$n.yaml" --rig-only
  $PY -m aoi3d_cli up --rig "$OUT/rig-$n.yaml" --port-offset "$OFF" --zenoh-port "$ZP" \
    --run-id "ingest-rate-$n" --quiet > "$OUT/up-$n.log" 2>&1 &
  UP=$!
  for _ in $(seq 1 120); do
    curl -sf "http://127.0.0.1:$((8105 + OFF))/healthz" >/dev/null \
      && curl -sf "http://127.0.0.1:$((8101 + OFF))/healthz" >/dev/null && break
    sleep 1
  done
  $PY -m aoi3d_cli ros2 publish "$D" --cameras "$n" --time-scale 1 --connect "tcp/127.0.0.1:$ZP" \
    --duration-s "$SECONDS_RUN" > "$OUT/robot-$n.log" 2>&1
  sleep 3
  curl -s "http://127.0.0.1:$((8101 + OFF))/status" > "$OUT/status-$n.json"
  kill -TERM $UP; wait $UP || true
  $PY - "$OUT" "$n" <<'PY'
import json, re, statistics, sys
out, n = sys.argv[1], sys.argv[2]
s = json.load(open(f"{out}/status-{n}.json"))
robot = open(f"{out}/robot-{n}.log").read()
m = re.search(r"published (\d+) images in (\d+) periods over ([\d.]+) s \((\d+) periods skipped", robot)
sent, periods, secs, skipped = int(m[1]), int(m[2]), float(m[3]), int(m[4])
cams = s["cameras"]
row = {"cameras": int(n) + 1, "sent": sent, "periods": periods, "seconds": secs,
       "periods_skipped": skipped, "sent_per_s": sent / secs,
       "published": sum(c["published"] for c in cams),
       "lost": sum(c["lost"] for c in cams),
       "rejected": sum(sum(c["rejected"].values()) for c in cams),
       "inbox_dropped": s["inbox"]["dropped"],
       "age_ms_median": statistics.median(c["age_ms_median"] for c in cams)}
row["published_share"] = row["published"] / sent
print(json.dumps(row))
open(f"{out}/rate-{n}.json", "w").write(json.dumps(row))
PY
done
