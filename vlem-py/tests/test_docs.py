"""Every `python` block of README.md and docs/*.md runs as written, so the examples cannot go
stale: from a fresh folder that holds the repository's `configs/` and `data/` as a clone does (no
`out/` yet, so a save must create its folder), one interpreter per file, the blocks of a file in
order (a later block may use what an earlier one made). A block whose fence says
`python skip: REASON` is a fragment and is left out; the reason must be given.
"""

import pathlib
import re
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^```python(?P<info>[^\n]*)\n(?P<code>.*?)^```$", re.S | re.M)


def blocks(page):
    """The runnable python blocks of `page`, and the fragments with their reasons."""
    runnable, skipped = [], []
    for found in FENCE.finditer(page.read_text()):
        info = found["info"].strip()
        if info.startswith("skip:") and info[len("skip:"):].strip():
            skipped.append(info)
        elif info:
            raise AssertionError(f"{page.name}: a python fence says {info!r}; only `skip: REASON` is known")
        else:
            runnable.append(found["code"])
    return runnable, skipped


def test_the_python_blocks_are_found():
    # The front page points at docs/python.md, whose first block is the tour's example.
    runnable, _ = blocks(REPO / "docs" / "python.md")
    assert runnable and "vlem.Pipeline(" in runnable[0] and "m.save(" in runnable[0]


@pytest.mark.parametrize("page", [p for p in PAGES if blocks(p)[0]], ids=lambda p: p.name)
def test_every_python_block_runs_as_written(page, tmp_path):
    for name in ["configs", "data"]:
        (tmp_path / name).symlink_to(REPO / name)
    code = "\n".join(blocks(page)[0])
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, f"{page.name}:\n{code}\n{done.stderr}"
    if page.name == "python.md":
        assert "white wall" in done.stdout
        assert (tmp_path / "out" / "map.vlem").stat().st_size > 0
