"""The protocol fingerprint (issue 69, item 6): every summary row carries a short hash of what
its numbers were scored under, and table, compare and check say in one line what differs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from e3cm_bench.storage.fingerprint import FINGERPRINT, differences, fingerprint, protocol_items, protocol_notes
from e3cm_bench.storage.run_config import RunConfig
from helpers import invoke

pytestmark = pytest.mark.slow  # three runs: about 7 s


@pytest.fixture(scope="module")
def runs(shared_data: Path, tmp_path_factory) -> tuple[Path, Path, Path]:
    """One run at --ransac-px 3 (the default), an --eval-only copy of it at 5, and one again at 3."""
    where = tmp_path_factory.mktemp("fingerprint")
    first = where / "a"
    result = invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", first, "--matcher", "sift",
                    "--max-side", 240, "--limit", 3)
    assert result.exit_code == 0, result.output
    copies = []
    for name, px in (("b", 5), ("c", 3)):
        copy = where / name
        shutil.copytree(first, copy)
        result = invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", copy, "--matcher",
                        "sift", "--max-side", 240, "--limit", 3, "--eval-only", "--ransac-px", px)
        assert result.exit_code == 0, result.output
        copies.append(copy)
    return first, *copies


def _fingerprint(run: Path) -> str:
    return str(pd.read_csv(run / "summary.csv", dtype={FINGERPRINT: str})[FINGERPRINT].iloc[0])


def test_every_summary_holds_its_fingerprint(runs):
    a, b, c = runs
    assert len(_fingerprint(a)) == 10
    assert _fingerprint(a) == _fingerprint(c) != _fingerprint(b)
    assert _fingerprint(a) == fingerprint(protocol_items(RunConfig.read(a / "config.yaml")))


def test_table_names_what_differs(runs, tmp_path):
    a, b, c = runs
    result = invoke("table", a, b, "--out", tmp_path / "t", "--no-paper")
    assert result.exit_code == 0, result.output
    notes = [line for line in result.output.splitlines() if line.startswith("note: protocol differs")]
    assert len(notes) == 1 and "evaluation.homography_ransac_px 3.0 -> 5.0" in notes[0], result.output
    same = invoke("table", a, c, "--out", tmp_path / "u", "--no-paper")
    assert same.exit_code == 0 and "protocol differs" not in same.output


def test_compare_names_what_differs(runs, tmp_path):
    a, b, _ = runs
    result = invoke("compare", a, b, "--out", tmp_path / "cmp")
    assert result.exit_code == 0, result.output
    assert "homography_ransac_px 3.0 -> 5.0" in " ".join(result.output.split())
    assert "homography_ransac_px 3.0 -> 5.0" in (tmp_path / "cmp" / "compare.md").read_text()


def test_check_names_what_differs(runs, tmp_path):
    a, b, _ = runs
    baseline = tmp_path / "baseline.csv"
    assert invoke("check", a, "--baseline", baseline, "--update").exit_code == 0
    moved = tmp_path / "moved" / "a"
    shutil.copytree(b, moved)  # the same method under another threshold
    result = invoke("check", moved, "--baseline", baseline)
    assert "homography_ransac_px 3.0 -> 5.0" in " ".join(result.output.split()), result.output


def test_items_cover_the_estimators_versions_and_the_sfm_protocol():
    config = {"benchmark": "sfm", "evaluation": {"seed": 0, "estimator": "opencv"},
              "dataset": {"protocol": {"mapper": "global", "merge": "auto"}},
              "identity": {"max_side": 1200, "resize": "shrink"},
              "versions": {"opencv-python-headless": "5.0.0.93", "pycolmap": "4.2.1"}}
    items = protocol_items(config)
    assert items["sfm.mapper"] == "global" and not any(name.startswith("image") for name in items)
    assert items["version.pycolmap"] == "4.2.1" and items["version.poselib"] == "not recorded"
    other = protocol_items({**config, "versions": {**config["versions"], "pycolmap": "4.3.0"}})
    assert differences(items, other) == ["version.pycolmap 4.2.1 -> 4.3.0"]
    assert protocol_notes([("x", items), ("y", items)]) == []
    assert "version.pycolmap" in protocol_notes([("x", items), ("y", other)])[0]


def test_an_sfm_protocol_in_the_evaluation_block_hashes_as_the_older_dataset_protocol_did():
    """sfm's reconstruction protocol moved from dataset.protocol to the evaluation block (issue 78):
    the same settings give the same items, so a run made before and one made after share a fingerprint."""
    protocol = {"mapper": "global", "mapper_seeds": 3, "merge": "auto", "merge_px": None, "verification": "estimator",
                "score_model": "any"}
    older = {"benchmark": "sfm", "evaluation": {"seed": 0, "estimator": "opencv"}, "dataset": {"protocol": protocol}}
    newer = {"benchmark": "sfm", "evaluation": {"seed": 0, "estimator": "opencv", **protocol}, "dataset": {}}
    assert protocol_items(newer) == protocol_items(older) and "sfm.mapper_seeds" in protocol_items(newer)
    changed = protocol_items({**newer, "evaluation": {**newer["evaluation"], "mapper_seeds": 1}})
    assert differences(protocol_items(newer), changed) == ["sfm.mapper_seeds 3 -> 1"]
