"""pycolmap 4.2.1 imported before Pillow makes Pillow's PNG writer abort the process; the
toolkit's one way in (ground.pycolmap.pycolmap_module) loads Pillow first."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("pycolmap")

SAVE = """
import numpy as np
{first}
from PIL import Image
for _ in range(10):
    Image.fromarray((np.random.default_rng(0).random((400, 400, 3)) * 255).astype("uint8")).save({path!r})
print("saved")
"""


def test_pngs_written_after_pycolmap_module(tmp_path):
    first = "from e3cm_bench.ground.pycolmap import pycolmap_module; pycolmap_module()"
    done = subprocess.run([sys.executable, "-c", SAVE.format(first=first, path=str(tmp_path / "x.png"))],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "saved" in done.stdout, done.stderr[-800:]
