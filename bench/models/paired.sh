#!/bin/bash
# The vlem model benchmarks of two builds in one sitting, alternating (before, after, before,
# after), best of each: how a change to the models is checked for regressions on the CPU ("no
# row may regress"), without the reference side. BEFORE and AFTER are folders holding the
# `clip_bench`, `dinov3_bench`, `naradio_bench` and `sam_bench` examples of each build (a git
# worktree of the old commit built into its own folder, e.g.
# `cargo build --release -p vlem-backends --features clip,dinov3,naradio,sam --example clip_bench
# --example dinov3_bench --example naradio_bench --example sam_bench`, then the examples copied).
#
#   bench/models/paired.sh BEFORE AFTER [THREADS...]      # default threads: 1 2
#   ONLY="CLIP text|NARADIO B" ROUNDS=3 bench/models/paired.sh BEFORE AFTER 2   # some rows, 3 rounds
#
# The CLIP rows need the random ViT-B/16 in /tmp/clip-vit-b16-random (bench/clip/make_random_b16.py);
# dinov3, NARADIO and SAM make their random full-size weights themselves. One markdown row per
# model and thread count: best ms of each build and after / before.
set -euo pipefail
cd "$(dirname "$0")/../.."
BEFORE=$1 AFTER=$2
shift 2
THREADS=("${@:-1}")
[ $# -eq 0 ] && THREADS=(1 2)
CLIP=/tmp/clip-vit-b16-random
ROUNDS=${ROUNDS:-2}

# name|example and arguments|pattern whose first group is the time in ms (dinov3 and NARADIO: the
# line's last figure, the mean of the process's runs, which is all that builds before 2026-12-07
# printed; the newer ones print the best first)
ROWS=(
  "CLIP image, 1 crop|clip_bench $CLIP --batch 1 --repeat 3|batch=1: best ([0-9.]+) ms/call"
  "CLIP image, 32 crops|clip_bench $CLIP --batch 32 --repeat 2|batch=32: best ([0-9.]+) ms/call"
  "CLIP text, 1 text|clip_bench $CLIP --text 1 --repeat 5|text=1x16: best ([0-9.]+) ms/call"
  "CLIP text, 80 texts|clip_bench $CLIP --text 80 --repeat 3|text=80x16: best ([0-9.]+) ms/call"
  "dinov3 ViT-L/16 + dino.txt, 592x448|dinov3_bench 448 2|([0-9.]+) ms/frame(?!.*ms/frame)"
  "NARADIO B/16, 640x480|naradio_bench b 2|([0-9.]+) ms/frame(?!.*ms/frame)"
  "NARADIO L/16, 640x480|naradio_bench l 2|([0-9.]+) ms/frame(?!.*ms/frame)"
  "SAM ViT-B image encoder|sam_bench --variant vit-b --points-per-side 32 --refine off|image encoder ([0-9.]+) ms"
  "SAM ViT-B mask decoder, per prompt|sam_bench --variant vit-b --points-per-side 32 --refine off|mask decoder ([0-9.]+) ms per prompt"
  "MobileSAM image encoder|sam_bench --variant mobile-sam --points-per-side 32 --refine off|image encoder ([0-9.]+) ms"
)

time_of() { # folder threads command pattern -> the ms one run reports
  local dir=$1 threads=$2 cmd=$3 pattern=$4 out
  out=$(RAYON_NUM_THREADS=$threads VLEM_BENCH_DEVICE=cpu "$dir"/$cmd 2>&1)
  python3 -c 'import re, sys; m = re.search(sys.argv[1], sys.stdin.read()); print(m.group(1) if m else "nan")' \
    "$pattern" <<<"$out"
}

echo "| model | threads | before ms | after ms | after / before |"
echo "|---|---|---:|---:|---:|"
for row in "${ROWS[@]}"; do
  IFS='|' read -r name cmd pattern <<<"$row"
  if [ -n "${ONLY:-}" ] && ! [[ $name =~ $ONLY ]]; then
    continue
  fi
  for t in "${THREADS[@]}"; do
    b=() a=()
    for _ in $(seq "$ROUNDS"); do
      b+=("$(time_of "$BEFORE" "$t" "$cmd" "$pattern")")
      a+=("$(time_of "$AFTER" "$t" "$cmd" "$pattern")")
    done
    python3 - "$name" "$t" "${b[*]}" "${a[*]}" <<'PY'
import sys
name, t, b, a = sys.argv[1], sys.argv[2], sys.argv[3].split(), sys.argv[4].split()
b, a = min(map(float, b)), min(map(float, a))
print(f"| {name} | {t} | {b:.1f} | {a:.1f} | {a / b:.3f} |")
PY
  done
done
