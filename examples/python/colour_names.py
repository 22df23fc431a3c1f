"""The colour-names encoder written again in numpy: an example of a vlem encoder in Python.

vlem's built-in ``colour-names`` encoder (Rust, ``plugins/vlem-plugin-colour-names``) embeds a pixel
as a soft assignment of its colour to the 11 basic colour terms of Berlin & Kay, and a text as the
colour words it names. This file computes the same embeddings with numpy only, so that it can be
read as the recipe for a Python encoder and so the tests can check a Python encoder against a Rust
one through the whole pipeline.

Use it from a config::

    [encoder]
    kind = "python"
    path = "examples/python/colour_names.py"   # or: module = "my_package.my_encoder"
    class = "ColourNames"

    [encoder.params]      # passed to the constructor as keyword arguments
    sigma = 15.0
    bins = 16

What vlem asks of an encoder class:

- ``dim`` (int): the embedding dimension of both sides;
- ``needs_regions`` (bool, optional, default False): whether ``encode_image`` gets the region
  proposer's regions;
- ``encode_image(rgb, regions)``: ``rgb`` is a ``uint8[h, w, 3]`` array, ``regions`` a list of
  regions (each with ``bbox = (x, y, width, height)`` and ``mask = bool[height, width]``; empty
  unless ``needs_regions``); returns either a region layout ``{"index": int[h, w], "table":
  float32[segments, dim]}`` (the segment of each pixel, ``-1`` for none, and one embedding row per
  segment) or a patch grid ``{"grid": float32[gh, gw, dim]}`` covering the whole image
  (``vlem.Regions`` and ``vlem.PatchGrid`` are the same with attributes);
- ``encode_text(text)`` (optional): a ``float32[dim]`` embedding of a query text.

A PyTorch model plugs in the same way: build it in ``__init__`` (on any device, ``cuda`` included),
run it under ``torch.inference_mode()`` in ``encode_image``, and return ``.cpu().numpy()`` arrays.
"""

import re

import numpy as np

TERMS = ["black", "white", "red", "green", "yellow", "blue", "brown", "purple", "pink", "orange", "grey"]

# The xkcd colour survey's sRGB colours for the terms (see the Rust crate's documentation).
PROTOTYPES_SRGB = np.array(
    [
        [0x00, 0x00, 0x00],
        [0xFF, 0xFF, 0xFF],
        [0xE5, 0x00, 0x00],
        [0x15, 0xB0, 0x1A],
        [0xFF, 0xFF, 0x14],
        [0x03, 0x43, 0xDF],
        [0x65, 0x37, 0x00],
        [0x7E, 0x1E, 0x9C],
        [0xFF, 0x81, 0xC0],
        [0xF9, 0x73, 0x06],
        [0x92, 0x95, 0x91],
    ],
    dtype=np.float64,
)

SYNONYMS = {
    "gray": "grey",
    "silver": "grey",
    "ivory": "white",
    "cream": "white",
    "crimson": "red",
    "scarlet": "red",
    "navy": "blue",
    "azure": "blue",
    "gold": "yellow",
    "golden": "yellow",
    "tan": "brown",
    "beige": "brown",
    "violet": "purple",
    "lilac": "purple",
    "lavender": "purple",
}


def srgb_to_lab(rgb):
    """sRGB (0..255, shape [..., 3]) to CIELAB with the D65 white, as the Rust encoder does."""
    c = np.clip(np.asarray(rgb, dtype=np.float64) / 255.0, 0.0, 1.0)
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array(
        [
            [0.4124564, 0.3575761, 0.1804375],
            [0.2126729, 0.7151522, 0.0721750],
            [0.0193339, 0.1191920, 0.9503041],
        ]
    )
    xyz = linear @ m.T / np.array([0.95047, 1.0, 1.08883])
    delta = 6.0 / 29.0
    f = np.where(xyz > delta**3, np.cbrt(xyz), xyz / (3.0 * delta * delta) + 4.0 / 29.0)
    return np.stack(
        [116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])],
        axis=-1,
    )


class ColourNames:
    """Soft assignment of colours to the 11 basic colour terms; one segment per colour bin."""

    dim = len(TERMS)
    needs_regions = False

    def __init__(self, sigma=15.0, bins=16):
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError(f"sigma must be a positive number of ΔE units (e.g. 15), got {sigma}")
        if not (2 <= int(bins) <= 64):
            raise ValueError(f"bins must be between 2 and 64 levels per channel (e.g. 16), got {bins}")
        self.sigma = float(sigma)
        self.bins = int(bins)
        self.prototypes = srgb_to_lab(PROTOTYPES_SRGB)

    def embed_colours(self, rgb):
        """Unit-norm embeddings of sRGB colours ``[n, 3]``."""
        lab = srgb_to_lab(rgb)
        d2 = ((lab[:, None, :] - self.prototypes[None, :, :]) ** 2).sum(axis=-1)
        d2 -= d2.min(axis=1, keepdims=True)
        w = np.exp(-d2 / (2.0 * self.sigma * self.sigma))
        return (w / np.linalg.norm(w, axis=1, keepdims=True)).astype(np.float32)

    def encode_image(self, rgb, regions):
        h, w, _ = rgb.shape
        level = (np.arange(256) * self.bins // 256).astype(np.int64)
        q = level[rgb.reshape(-1, 3)]
        bin_of_pixel = (q[:, 0] * self.bins + q[:, 1]) * self.bins + q[:, 2]
        # Occupied bins become segments 0, 1, ... in bin order, each embedded from its mean colour.
        occupied, segment_of_pixel, counts = np.unique(bin_of_pixel, return_inverse=True, return_counts=True)
        sums = np.zeros((len(occupied), 3), dtype=np.float64)
        np.add.at(sums, segment_of_pixel, rgb.reshape(-1, 3).astype(np.float64))
        table = self.embed_colours(sums / counts[:, None])
        # A plain dict, so the file needs only numpy (also inside the `vlem` binary).
        return {"index": segment_of_pixel.reshape(h, w).astype(np.int32), "table": table}

    def encode_text(self, text):
        counts = np.zeros(self.dim, dtype=np.float32)
        for word in re.split(r"[^\w]|[\d_]", text.lower()):
            term = SYNONYMS.get(word, word)
            if term in TERMS:
                counts[TERMS.index(term)] += 1.0
        norm = np.linalg.norm(counts)
        if norm == 0.0:
            raise ValueError(f"the colour-names encoder understands only colour words; {text!r} contains none")
        return counts / norm
