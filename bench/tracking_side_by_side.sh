#!/usr/bin/env bash
# vlem's two dense trackers side by side with Open3D 0.19's on the same frames, in one run:
# ms per frame (tracking only, image loading excluded on both sides) and RPE/ATE against the same
# pseudo ground truth. Run on a quiet machine: every timing here shares the same cores.
#
#   bash bench/setup-open3d.sh                 # once: bench/.venv with open3d==0.19.0
#   bash bench/tracking_side_by_side.sh [SEQUENCE_DIR]
#
# SEQUENCE_DIR defaults to ../shared/data/icl-livingroom1 (150 frames, Open3D's offline
# trajectory as pseudo ground truth). Results: out/bench/tracking-side-by-side.json and a table.
#
# REPEATS (default 3) rounds run both sides in turn (vlem's two trackers, then Open3D's), and the
# table gives each side's median ms per frame over the rounds and the ratio of the medians, with
# each round's ratio beside it: on a shared VM the speed of the machine drifts by a third over
# minutes, and alternating the sides keeps that drift out of the ratio. Trajectories and RPE come
# from the first round (both sides are deterministic).
set -euo pipefail
cd "$(dirname "$0")/.."
SEQ="${1:-../shared/data/icl-livingroom1}"
REF="$SEQ/trajectory_open3d_estimate.log"
REPEATS="${REPEATS:-3}"
OUT=out/bench
mkdir -p "$OUT"
# The table reads every round's files: none may be left over from an earlier run.
rm -f "$OUT"/open3d-tracking-round*.json "$OUT"/vlem-*/stats-round*.json

cargo build --release --quiet
have_open3d=false
if [ -x bench/.venv/bin/python ]; then
  have_open3d=true
else
  echo "bench/.venv missing: run bench/setup-open3d.sh for the Open3D side" >&2
fi
for round in $(seq 1 "$REPEATS"); do
  for tracker in odometry frame-to-model; do
    target/release/vlem run --config "configs/track-$tracker.toml" --dataset "$SEQ" \
      --out "$OUT/vlem-$tracker" --no-colour-model
    cp "$OUT/vlem-$tracker/stats.json" "$OUT/vlem-$tracker/stats-round$round.json"
    if [ "$round" = 1 ]; then
      target/release/vlem eval trajectory --estimate "$OUT/vlem-$tracker/trajectory.tum" \
        --reference "$REF" --json "$OUT/vlem-$tracker/eval.json" > /dev/null
    fi
  done
  if $have_open3d; then
    bench/.venv/bin/python bench/open3d_tracking.py "$SEQ" --out "$OUT"
    cp "$OUT/open3d-tracking.json" "$OUT/open3d-tracking-round$round.json"
    if [ "$round" = 1 ]; then
      for tracker in odometry frame-to-model; do
        target/release/vlem eval trajectory --estimate "$OUT/open3d-$tracker.tum" \
          --reference "$REF" --json "$OUT/open3d-$tracker-eval.json" > /dev/null
      done
    fi
  fi
done

python3 - "$OUT" "$REPEATS" <<'PY'
import json, os, statistics, sys
out, repeats = sys.argv[1], int(sys.argv[2])
def load(path):
    return json.load(open(path)) if os.path.exists(path) else None
rounds = range(1, repeats + 1)
o3d_rounds = [load(f"{out}/open3d-tracking-round{r}.json") for r in rounds]
rows = {}
for tracker, key in [("odometry", "odometry"), ("frame-to-model", "frame_to_model")]:
    stats = load(f"{out}/vlem-{tracker}/stats.json")
    ours = load(f"{out}/vlem-{tracker}/eval.json")
    theirs = load(f"{out}/open3d-{tracker}-eval.json")
    vlem_ms = [load(f"{out}/vlem-{tracker}/stats-round{r}.json")["mean_ms"]["track"] for r in rounds]
    row = {
        "rounds": repeats,
        "vlem_ms_per_frame_rounds": vlem_ms,
        "vlem_ms_per_frame": statistics.median(vlem_ms),
        "vlem_rpe_trans_rmse_m": ours["rpe"]["translation_m"]["rmse"],
        "vlem_rpe_rot_rmse_deg": ours["rpe"]["rotation_deg"]["rmse"],
        "vlem_ate_rmse_m": ours["ate"]["position_m"]["rmse"],
        "vlem_frames_lost": stats["frames"]["lost"],
    }
    if all(o3d_rounds) and theirs:
        o3d_ms = [o[key]["timing_per_frame"]["mean_ms"] for o in o3d_rounds]
        row.update({
            "open3d_ms_per_frame_rounds": o3d_ms,
            "open3d_ms_per_frame": statistics.median(o3d_ms),
            "open3d_rpe_trans_rmse_m": theirs["rpe"]["translation_m"]["rmse"],
            "open3d_rpe_rot_rmse_deg": theirs["rpe"]["rotation_deg"]["rmse"],
            "open3d_ate_rmse_m": theirs["ate"]["position_m"]["rmse"],
        })
        row["time_ratio_rounds"] = [v / o for v, o in zip(vlem_ms, o3d_ms)]
        row["time_ratio_vlem_over_open3d"] = row["vlem_ms_per_frame"] / row["open3d_ms_per_frame"]
        row["rpe_ratio_vlem_over_open3d"] = row["vlem_rpe_trans_rmse_m"] / row["open3d_rpe_trans_rmse_m"]
    rows[tracker] = row
json.dump(rows, open(f"{out}/tracking-side-by-side.json", "w"), indent=1)
print(f"median of {repeats} rounds (ms/frame); RPE and ATE from the first round")
print(f"{'tracker':16} {'side':7} {'ms/frame':>9} {'RPE mm':>8} {'RPE deg':>8} {'ATE cm':>7}  rounds")
for tracker, r in rows.items():
    for side in ["vlem", "open3d"]:
        if f"{side}_ms_per_frame" in r:
            each = " ".join(f"{ms:.1f}" for ms in r[side + "_ms_per_frame_rounds"])
            print(f"{tracker:16} {side:7} {r[side + '_ms_per_frame']:9.1f} "
                  f"{1e3 * r[side + '_rpe_trans_rmse_m']:8.2f} {r[side + '_rpe_rot_rmse_deg']:8.3f} "
                  f"{1e2 * r[side + '_ate_rmse_m']:7.2f}  {each}")
    if "time_ratio_vlem_over_open3d" in r:
        each = " ".join(f"{x:.2f}" for x in r["time_ratio_rounds"])
        print(f"{tracker:16} ratio   time {r['time_ratio_vlem_over_open3d']:.2f}x (rounds {each}), "
              f"RPE {r['rpe_ratio_vlem_over_open3d']:.2f}x (vlem / Open3D)")
PY
