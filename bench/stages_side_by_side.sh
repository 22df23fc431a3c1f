#!/bin/bash
# Serial and overlapped embedding stages side by side, in one sitting, alternating: for each config,
# an offline run (every frame embedded: the embedding rate is frames / run seconds) and a run in the
# config's own real-time mode (frames integrated of those replayed at its frame rate), with each
# `[pipeline] stages` layout. Prints one line per run and the median of each.
#
#   bench/stages_side_by_side.sh [CONFIG ...]     # default: the two CPU real-time model configs
#
# Environment: VLEM (the binary; default target/release/vlem, built with --features clip,graph,naradio),
# DATASET (default ../shared/data/icl-livingroom1), OFFLINE_FRAMES (default 30), REPEATS (default 2),
# and the model folders the configs read (VLEM_CLIP_DIR, VLEM_NARADIO_DIR: random-weight folders
# from bench/clip/make_random_b16.py and bench/naradio/make_random.py have the real models' speed).
set -euo pipefail
cd "$(dirname "$0")/.."
VLEM=${VLEM:-target/release/vlem}
DATASET=${DATASET:-../shared/data/icl-livingroom1}
OFFLINE_FRAMES=${OFFLINE_FRAMES:-30}
REPEATS=${REPEATS:-2}
if [ $# -eq 0 ]; then
    set -- configs/realtime-cpu-clip.toml configs/realtime-cpu-naradio.toml
fi
work=$(mktemp -d)
# The variant configs sit beside the originals so that their relative paths still resolve.
variants=()
trap 'rm -rf "$work"; rm -f "${variants[@]}"' EXIT

# variant CONFIG MODE STAGES: a copy of CONFIG with [pipeline] mode and stages set; prints its path.
variant() {
    local config=$1 mode=$2 stages=$3
    local out
    out="$(dirname "$config")/.bench-stages-$(basename "$config" .toml)-$mode-$stages.toml"
    python3 - "$config" "$mode" "$stages" >"$out" <<'EOF'
import re, sys
text = open(sys.argv[1]).read()
mode, stages = sys.argv[2], sys.argv[3]
text = re.sub(r'(?m)^(mode|stages)\s*=.*\n', '', text)
setting = f'mode = "{mode}"\nstages = "{stages}"\n'
if re.search(r'(?m)^\[pipeline\]\s*$', text):
    text = re.sub(r'(?m)^\[pipeline\]\s*\n', '[pipeline]\n' + setting, text, count=1)
else:
    text += '\n[pipeline]\n' + setting
print(text, end='')
EOF
    variants+=("$out")
    echo "$out"
}

# One run; prints "processed total wall busy(stage=ms ...)" from its stats.json.
one_run() {
    local config=$1 frames=$2 out=$work/out
    rm -rf "$out"
    local limit=()
    [ -n "$frames" ] && limit=(--max-frames "$frames")
    "$VLEM" run --config "$config" --dataset "$DATASET" --out "$out" --no-colour-model "${limit[@]}" >/dev/null 2>"$work/err" || {
        cat "$work/err" >&2
        return 1
    }
    python3 - "$out/stats.json" <<'EOF'
import json, sys
s = json.load(open(sys.argv[1]))
busy = " ".join(f"{k}={v['busy']['total_ms']:.0f}" for k, v in s["stage_load"].items())
print(s["frames"]["processed"], s["frames"]["total"], f'{s["wall_seconds"]:.2f}', busy)
EOF
}

for config in "$@"; do
    name=$(basename "$config" .toml)
    for mode in offline real-time; do
        frames=""
        [ "$mode" = offline ] && frames=$OFFLINE_FRAMES
        serial=$(variant "$config" "$mode" serial)
        overlapped=$(variant "$config" "$mode" overlapped)
        : >"$work/$name-$mode-serial" && : >"$work/$name-$mode-overlapped"
        for round in $(seq "$REPEATS"); do
            for stages in serial overlapped; do
                file=$serial
                [ "$stages" = overlapped ] && file=$overlapped
                line=$(one_run "$file" "$frames")
                echo "$name $mode round $round $stages: processed total wall_s busy_ms = $line"
                echo "$line" >>"$work/$name-$mode-$stages"
            done
        done
        python3 - "$name" "$mode" "$work/$name-$mode-serial" "$work/$name-$mode-overlapped" <<'EOF'
import statistics, sys
name, mode, serial, overlapped = sys.argv[1:5]
def rows(path):
    return [line.split() for line in open(path) if line.strip()]
def median(path, offline):
    r = rows(path)
    if offline:  # frames per second of run time
        return statistics.median(int(x[0]) / float(x[2]) for x in r), "frames/s"
    return statistics.median(int(x[0]) for x in r), f"of {r[0][1]} frames integrated"
offline = mode == "offline"
s, unit = median(serial, offline)
o, _ = median(overlapped, offline)
print(f"== {name} {mode}: serial {s:.2f}, overlapped {o:.2f} {unit} (median; overlapped/serial {o / s if s else float('nan'):.2f})")
EOF
    done
done
