#!/usr/bin/env bash
# What a `GET /map.vlem` download holds: the server's resident memory before and after each of N
# downloads one at a time, and its peak while FOUR clients download at once (the server sends two
# at a time and answers the others 503). Maps the shared living-room sequence with the demo's
# stages first (992k points, a 58.5 MB map file).
#
#   bench/server/download_memory.sh [N] [DATASET]      (release build of `vlem`, curl)
set -euo pipefail
cd "$(dirname "$0")/../.."
N=${1:-8}
DATASET=${2:-../shared/data/icl-livingroom1}
cargo build --release --quiet --bin vlem
OUT=$(mktemp -d)
PORT_FILE=$OUT/stderr
./target/release/vlem run --config configs/demo.toml --dataset "$DATASET" --out "$OUT/run" \
    --serve 127.0.0.1:0 --serve-after 2> "$PORT_FILE" &
PID=$!
trap 'kill $PID 2>/dev/null; rm -rf "$OUT"' EXIT
ADDRESS=
for _ in $(seq 600); do
    ADDRESS=$(grep -o 'serving the live map on http://[0-9.:]*' "$PORT_FILE" | sed 's|.*http://||' || true)
    [ -n "$ADDRESS" ] && break
    sleep 0.1
done
until curl -s "http://$ADDRESS/status" | grep -q '"state":"finished"'; do sleep 0.5; done
rss() { awk '/VmRSS/ {printf "%.1f", $2 / 1024}' "/proc/$PID/status"; }
echo "{\"event\": \"mapped\", \"rss_mb\": $(rss)}"
for i in $(seq "$N"); do
    curl -s -o /dev/null -w '' "http://$ADDRESS/map.vlem"
    echo "{\"event\": \"download\", \"n\": $i, \"rss_mb\": $(rss)}"
done
PEAK=0
CLIENTS=()
for _ in 1 2 3 4; do
    curl -s -o /dev/null -w '%{http_code}\n' "http://$ADDRESS/map.vlem" >> "$OUT/codes" &
    CLIENTS+=($!)
done
running() { for c in "${CLIENTS[@]}"; do kill -0 "$c" 2>/dev/null && return 0; done; return 1; }
while running; do
    NOW=$(rss); PEAK=$(awk -v a="$PEAK" -v b="$NOW" 'BEGIN {print (b > a) ? b : a}')
    sleep 0.02
done
echo "{\"event\": \"four_at_once\", \"answers\": \"$(sort "$OUT/codes" | uniq -c | tr -s ' ' | tr '\n' ';')\", \"peak_rss_mb\": $PEAK, \"rss_mb\": $(rss)}"
