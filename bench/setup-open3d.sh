#!/usr/bin/env bash
# Creates bench/.venv with Open3D 0.19.0 (CPU wheel from PyPI) + numpy for the Open3D tracking anchors.
# Usage: bash bench/setup-open3d.sh   (from anywhere; PYTHON=python3.11 to pick an interpreter)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
py="${PYTHON:-python3}"
if [ ! -x "$here/.venv/bin/python" ]; then
  "$py" -m venv "$here/.venv"
fi
"$here/.venv/bin/python" -m pip install --upgrade pip >/dev/null
"$here/.venv/bin/python" -m pip install "open3d==0.19.0" numpy
"$here/.venv/bin/python" -c 'import open3d as o3d, numpy as np; print("open3d", o3d.__version__, "numpy", np.__version__, "cuda", o3d.core.cuda.is_available())'
