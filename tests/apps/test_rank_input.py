"""`rank`'s input checked before a matcher starts: one line naming what is wrong, a non-zero exit, no run made."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers import invoke

pytest.importorskip("pycolmap")


def test_a_folder_without_images_is_one_line_before_any_matcher_runs(tmp_path: Path):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "notes.txt").write_text("not an image")
    result = invoke("rank", photos, "--out", tmp_path / "out", "--matchers", "sift,xfeat,orb-none")
    assert result.exit_code == 2, result.output  # bad input, as every command gives it
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and str(photos) in lines[0] and "holds 0 image(s)" in lines[0], result.output
    assert not (tmp_path / "out" / "runs").exists()


def test_two_matchers_are_refused_since_each_would_only_be_the_others_distance(tmp_path: Path):
    photos = tmp_path / "photos"
    photos.mkdir()
    result = invoke("rank", photos, "--out", tmp_path / "out", "--matchers", "sift,xfeat")
    assert result.exit_code != 0 and "at least 3 matchers" in result.output, result.output
