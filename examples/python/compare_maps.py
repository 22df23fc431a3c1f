# %% [markdown]
# # Which map representation, for how much memory?
#
# A small comparison study in the style of the paper's Fig. 4, run from Python: every map this
# build of vlem contains, at two resolutions, on a labelled sequence; each cell is mapped and
# evaluated (3D semantic segmentation, the paper's protocol) in a process of its own, and the table
# comes back as a list of dicts (a pandas DataFrame when pandas is installed). With matplotlib
# installed it plots mIoU against peak memory.
#
#     python examples/python/compare_maps.py                     # the synthetic labelled scene
#     python examples/python/compare_maps.py --dataset DIR       # a labelled folder of your own
#     python examples/python/compare_maps.py --frames 20 --out out/compare-maps
#
# The cells start with `# %%`, so editors that run notebook cells (VS Code, Jupytext, Spyder) run
# it cell by cell too. It needs only numpy besides vlem; pandas and matplotlib are optional.

# %%
import argparse
import json
import pathlib
import sys

import vlem

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--dataset", help="a labelled dataset folder (label/ and labels.json)")
parser.add_argument("--frames", type=int, default=12, help="frames per cell")
parser.add_argument("--out", default="out/compare-maps", help="output folder")
args = parser.parse_args(sys.argv[1:] if "ipykernel" not in sys.modules else [])
out = pathlib.Path(args.out)
out.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# The base config: ground-truth poses, the weight-free colour-names encoder, and the sequence.
# Colour-names knows only colour words, so every class is queried by a colour (a real VLM encoder
# queries the class names themselves: leave `prompts` out).

# %%
if args.dataset:
    dataset = {"path": str(pathlib.Path(args.dataset).resolve())}
else:
    dataset = {"kind": "synthetic", "synthetic": {"seed": 2, "frames": args.frames, "width": 160, "height": 120}}
colours = ["white", "brown", "grey", "red", "blue", "green"]
prompts = {name: colours[i % len(colours)] for i, name in enumerate(vlem.class_names())}
(out / "prompts.json").write_text(json.dumps(prompts))


def toml(header, table):
    """One TOML table: `header` (e.g. "[dataset]" or "[[maps]]"), its scalars, then its tables."""
    lines = [header] + [f"{k} = {json.dumps(v)}" for k, v in table.items() if not isinstance(v, dict)]
    name = header.strip("[]")
    lines += [toml(f"[{name}.{k}]", v) for k, v in table.items() if isinstance(v, dict)]
    return "\n".join(lines)


base = {"dataset": dataset, "tracker": {"kind": "ground-truth"}, "encoder": {"kind": "colour-names"}}
(out / "base.toml").write_text("\n\n".join(toml(f"[{k}]", v) for k, v in base.items()) + "\n")

# %% [markdown]
# The variants: each map this build has, coarse and fine.

# %%
built = {p["name"] for p in vlem.plugins() if p["stage"] == "map"}
variants = {
    "point-cloud": [("point-cloud 2 cm", {"max_distance": 0.02}), ("point-cloud 5 cm", {"max_distance": 0.05})],
    "voxel": [("voxel 2 cm", {"voxel_size": 0.02}), ("voxel 5 cm", {"voxel_size": 0.05})],
    "segment": [("segment", {})],
}
maps = []
for kind, settings in variants.items():
    if kind in built:
        for name, params in settings:
            maps.append(toml("[[maps]]", {"name": name, "kind": kind, **params}))
study_file = out / "study.toml"
study_file.write_text(
    '[study]\nbase = "base.toml"\nprompts = "prompts.json"\n'
    f"max_frames = {args.frames}\n\n" + "\n\n".join(maps) + "\n"
)
for cell in vlem.study_cells(study_file):
    print(f"cell {cell['index']}: {cell['map']}")

# %% [markdown]
# Run it. Finished cells are kept in `out/cells/`, so running the script again only runs what is
# missing (`force=True` runs everything again).

# %%
table = vlem.study(
    study_file,
    out,
    progress=lambda e: e["event"] == "finished" and print(f"  {e['label']}: {e['status']}"),
)
for row in table:
    if row["status"] == "ok":
        mib = row["peak_resident_bytes"] / 2**20
        print(f"{row['map']:<18} mIoU {100 * row['miou']:5.1f} %   peak {mib:7.1f} MiB   {row['map_points']:>8} points")
    else:
        print(f"{row['map']:<18} failed: {row['error']}")

# %%
try:
    frame = table.to_dataframe()
    print(frame[["map", "miou", "map_points", "map_bytes", "peak_resident_bytes", "integrate_ms"]])
except ImportError:
    print("(pip install pandas for the table as a DataFrame)")

# %% [markdown]
# mIoU against peak memory, one marker per map.

# %%
try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    print("(pip install matplotlib for the plot)")
else:
    done = [r for r in table if r["status"] == "ok"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in done:
        ax.scatter(row["peak_resident_bytes"] / 2**20, 100 * row["miou"], s=60, label=row["map"])
    ax.legend(loc="best")
    ax.set_xlabel("peak resident memory of the mapping (MiB)")
    ax.set_ylabel("mIoU (%)")
    ax.set_title("map representations: mIoU against memory")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "compare-maps.png", dpi=120)
    print(f"plot: {out / 'compare-maps.png'}")
