"""`e3cm-bench match`: the demo pair, a real HPatches pair, and its one-line errors.

In-process through `typer.testing.CliRunner`; the offline EfficientNet-Lite0 backbone only.
Measured numbers (torch 2.15 CPU, opencv 5.0) are noted next to their margins.
"""

from __future__ import annotations

import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import e3cm_bench.backbones.loading as backbones_module
from e3cm_bench.geometry import two_view as geometry
from e3cm_bench.datasets.hpatches import read_homography
from e3cm_bench.apps.synth.textures import demo_pair
from helpers import flat, invoke, one_line_error


def load_matches(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        assert sorted(data.files) == ["keypoints0", "keypoints1", "scores"]
        return {key: data[key] for key in data.files}


@pytest.fixture(scope="module")
def graffiti(shared_data: Path) -> Path:
    return shared_data / "hpatches-sequences-release" / "v_graffiti"


def test_demo_pair(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = invoke("match")
    assert result.exit_code == 0, (result.output, result.exception)
    out = tmp_path / "e3cm-match"
    m = load_matches(out / "matches.npz")
    n = len(m["keypoints0"])
    assert m["keypoints0"].shape == m["keypoints1"].shape == (n, 2) and m["scores"].shape == (n,)
    assert np.all(np.isfinite(m["keypoints0"])) and np.all(np.isfinite(m["scores"]))
    # Measured: 3234 matches, 87.7% within 3 px of the demo homography.
    assert n > 500
    image = cv2.imread(str(out / "matches.png"))
    assert image is not None and image.shape[1] >= 2 * 640 - 1

    text = flat(result.output)
    assert "backbone efficientnet_lite0" in text
    assert f"{n} matches (e3cm, efficientnet_lite0)" in text
    # The printed accuracy is that of the saved matches against the demo's homography.
    _, _, H = demo_pair()
    errors = np.linalg.norm(geometry.warp_points(H, m["keypoints0"].astype(np.float64)) - m["keypoints1"], axis=1)
    accuracy = 100 * np.mean(errors <= 3.0)
    assert f"demo ground truth: {accuracy:.1f}% of matches within 3 px" in text
    assert accuracy > 70
    times = re.search(r"time per stage \(s\): (.*)", text)
    assert times, text
    # The allocator is a developer's detail: not on the console (match --verbose prints it).
    assert "allocator" not in text, text
    stages = times.group(1)
    for stage in ("model load", "backbone", "initial", "refine", "cascade"):
        assert re.search(rf"{stage}\S* \d+\.\d{{3}}", stages), (stage, stages)
    assert re.search(r"matches per level .* L0: \d+->" + str(n), text)


def test_match_two_images(graffiti, tmp_path):
    out = tmp_path / "out"
    result = invoke("match", graffiti / "1.ppm", graffiti / "2.ppm", "--backbone", "efficientnet_lite0",
                    "--max-side", 400, "--matcher", "direct", "--out", out, "--verbose")
    assert result.exit_code == 0, (result.output, result.exception)
    m = load_matches(out / "matches.npz")
    n = len(m["keypoints0"])
    assert len(m["keypoints1"]) == len(m["scores"]) == n
    # --verbose adds the allocator's set-up (the second pass reuses the first's pages, as in a run).
    if platform.libc_ver()[0] == "glibc" and os.environ.get("E3CM_BENCH_ALLOCATOR") != "system":
        assert "allocator: glibc, freed memory kept" in flat(result.output), result.output
    else:
        assert "allocator: system" in flat(result.output), result.output
    assert (out / "matches.png").is_file()
    text = flat(result.output)
    assert f"{n} matches (direct, efficientnet_lite0)" in text
    assert "demo ground truth" not in text
    assert "cascade 0.000" in text  # direct = the cascade switched off
    # Matched at 400 x 320, reported in the original 800 x 640 pixels.
    assert m["keypoints0"][:, 0].max() > 400 and m["keypoints0"][:, 0].max() < 800
    assert m["keypoints1"][:, 1].max() > 320 and m["keypoints1"][:, 1].max() < 640
    H = read_homography(graffiti / "H_1_2")
    errors = np.linalg.norm(geometry.warp_points(H, m["keypoints0"].astype(np.float64)) - m["keypoints1"], axis=1)
    print(f"{n} matches, within 3 px: {np.mean(errors <= 3):.3f}, within 10 px: {np.mean(errors <= 10):.3f}")
    # Measured: 1208 matches, 47.4% within 3 px, 85.3% within 10 px (of image 1's 800 x 640).
    assert 600 <= n <= 2000
    assert abs(np.mean(errors <= 3) - 0.474) <= 0.15
    assert np.mean(errors <= 10) >= 0.70


def test_one_image_is_an_error(graffiti, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = one_line_error(invoke("match", graffiti / "1.ppm"))
    assert "two images" in line
    assert not (tmp_path / "e3cm-match").exists()


def test_missing_image_is_an_error(graffiti, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    missing = tmp_path / "nope.ppm"
    line = one_line_error(invoke("match", graffiti / "1.ppm", missing, "--backbone", "efficientnet_lite0"))
    assert str(missing) in line
    assert not (tmp_path / "e3cm-match").exists()


def test_debug_variable_shows_the_exception(graffiti, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("E3CM_BENCH_DEBUG", "1")
    result = invoke("match", graffiti / "1.ppm", tmp_path / "nope.ppm", "--backbone", "efficientnet_lite0")
    assert isinstance(result.exception, ValueError) and "nope.ppm" in str(result.exception)


def test_vgg19_without_weights_offline(graffiti, tmp_path, monkeypatch):
    torch_home = tmp_path / "torch_home"
    torch_home.mkdir()
    monkeypatch.setenv("TORCH_HOME", str(torch_home))
    monkeypatch.setattr(backbones_module, "imagenet_weights_url", lambda spec: "http://127.0.0.1:9/vgg19-dcbb9e9d.pth")
    out = tmp_path / "out"
    line = one_line_error(invoke("match", graffiti / "1.ppm", graffiti / "2.ppm", "--backbone", "vgg19",
                                 "--max-side", 320, "--out", out))
    expected = torch_home / "hub" / "checkpoints" / "vgg19-dcbb9e9d.pth"
    assert str(expected) in line
    assert "--weights" in line and "vgg19" in line
    assert "--backbone efficientnet_lite0" in line  # the offline way, named where it is needed
    assert not expected.exists() and not out.exists()


def test_missing_image_console_script_one_line(graffiti, tmp_path):
    """The real console script in a subprocess: stderr holds exactly the one error line."""
    script = Path(sys.executable).parent / "e3cm-bench"
    if not script.is_file():
        pytest.skip(f"console script not installed next to {sys.executable}")
    missing = tmp_path / "nope.ppm"
    proc = subprocess.run([str(script), "match", str(graffiti / "1.ppm"), str(missing)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300)
    print(proc.stdout, proc.stderr)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and str(missing) in lines[-1]
    assert len(lines) == 1, lines
