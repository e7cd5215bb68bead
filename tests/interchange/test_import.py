"""Matches made elsewhere: hloc files and npz folders written from a native sift run
import into run folders that evaluate to the same numbers; bad sources give one line."""

from __future__ import annotations

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from e3cm_bench.storage.cache import MatchCache
from e3cm_bench.pipeline.imported import hloc_pair_key
from helpers import accuracy_summary, invoke, one_line_error


@pytest.fixture(scope="module")
def native(shared_data, tmp_path_factory):
    """A native sift run on v_boat and v_graffiti (10 pairs) and what it matched, by pair."""
    root = shared_data / "hpatches-sequences-release"
    out = tmp_path_factory.mktemp("native") / "sift"
    result = invoke("hpatches", "--root", root, "--out", out, "--matcher", "sift", "--sequences", "v_boat",
                    "--sequences", "v_graffiti")
    assert result.exit_code == 0
    cache = MatchCache(out / "matches.h5")
    return root, out, {name: cache.read(name) for name in cache.names()}


def image_of(pair: str, side: int) -> str:
    """v_boat/1-3 -> v_boat/1.ppm (side 0) or v_boat/3.ppm (side 1): the images' names
    relative to the root, as hloc names them."""
    sequence, ids = pair.split("/")
    return f"{sequence}/{ids.split('-')[side]}.ppm"


def write_hloc(matches: dict, features_path, matches_path, reversed_pairs=()) -> None:
    """hloc's layout from per-pair matches: one keypoint list per image (each pair's matched
    points appended to its images' lists; points may repeat, as sift's do at one location with
    two orientations), and per pair matches0 from the first image's list into the second's
    (some pairs stored second image first)."""
    points: dict[str, list] = {}
    segment: dict[tuple[str, int], int] = {}  # (pair, side) -> offset of its points in the image's list
    for pair, m in matches.items():
        for side, k in ((0, m.keypoints0), (1, m.keypoints1)):
            listed = points.setdefault(image_of(pair, side), [])
            segment[pair, side] = sum(len(x) for x in listed)
            listed.append(k)
    keypoints = {name: np.concatenate(ks) for name, ks in points.items()}
    with h5py.File(features_path, "w") as f:
        for name, k in keypoints.items():
            f.create_group(name).create_dataset("keypoints", data=k)
    with h5py.File(matches_path, "w") as f:
        for pair, m in matches.items():
            sides = (1, 0) if pair in reversed_pairs else (0, 1)
            first, second = (image_of(pair, side) for side in sides)
            n = len(m.keypoints0)
            matches0 = np.full(len(keypoints[first]), -1, int)
            scores0 = np.zeros(len(keypoints[first]), np.float32)
            rows = segment[pair, sides[0]] + np.arange(n)
            matches0[rows], scores0[rows] = segment[pair, sides[1]] + np.arange(n), m.scores
            group = f.create_group(hloc_pair_key(first, second))
            group.create_dataset("matches0", data=matches0)
            group.create_dataset("matching_scores0", data=scores0)


def same_results(native_out, imported_out) -> None:
    a, b = (pd.read_csv(d / "per_pair.csv").sort_values("pair").reset_index(drop=True) for d in (native_out, imported_out))
    pd.testing.assert_frame_equal(a, b)
    # the native run's cost columns (its time and memory) are its own: imported matches have none
    sa, sb = (accuracy_summary(d / "summary.csv") for d in (native_out, imported_out))
    pd.testing.assert_frame_equal(sa, sb)


def test_hloc_files_import_to_the_same_numbers_as_the_native_run(native, tmp_path):
    root, native_out, matches = native
    assert len(matches) == 10
    write_hloc(matches, tmp_path / "feats.h5", tmp_path / "matches.h5", reversed_pairs={"v_boat/1-3", "v_graffiti/1-6"})
    out = tmp_path / "imported"
    result = invoke("import", "hpatches", "--root", root, "--out", out, "--hloc", tmp_path / "feats.h5",
                    tmp_path / "matches.h5", "--sequences", "v_boat", "--sequences", "v_graffiti", "--label", "sift-hloc")
    assert result.exit_code == 0
    same_results(native_out, out)
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["method"] == "sift-hloc" and config["identity"]["imported"]["format"] == "hloc"
    assert set(config["identity"]["imported"]["files"]) == {"features", "matches"}
    assert all(len(v) == 64 for v in config["identity"]["imported"]["files"].values())
    # it is a run like any: table and check read it
    assert invoke("table", out, "--out", tmp_path / "t" / "table", "--no-compare").exit_code == 0
    assert "sift-hloc" in (tmp_path / "t" / "table.md").read_text()
    assert invoke("check", out, "--baseline", tmp_path / "base.csv", "--update").exit_code == 0
    assert invoke("check", out, "--baseline", tmp_path / "base.csv").exit_code == 0
    # other source files in the same folder are refused; the same ones resume (nothing to redo)
    assert invoke("import", "hpatches", "--root", root, "--out", out, "--hloc", tmp_path / "feats.h5",
                  tmp_path / "matches.h5", "--sequences", "v_boat", "--sequences", "v_graffiti",
                  "--label", "sift-hloc").exit_code == 0
    with h5py.File(tmp_path / "matches.h5", "a") as f:
        f.attrs["touched"] = 1
    line = one_line_error(invoke("import", "hpatches", "--root", root, "--out", out, "--hloc", tmp_path / "feats.h5",
                                 tmp_path / "matches.h5", "--sequences", "v_boat", "--sequences", "v_graffiti"))
    assert "came from elsewhere (imported)" in line and "--overwrite" in line


def test_an_npz_folder_imports_to_the_same_numbers_as_the_native_run(native, tmp_path):
    root, native_out, matches = native
    folder = tmp_path / "npz"
    for pair, m in matches.items():
        (folder / pair).parent.mkdir(parents=True, exist_ok=True)
        np.savez(folder / f"{pair}.npz", keypoints0=m.keypoints0, keypoints1=m.keypoints1, scores=m.scores)
    out = tmp_path / "imported"
    result = invoke("import", "hpatches", "--root", root, "--out", out, "--npz", folder,
                    "--sequences", "v_boat", "--sequences", "v_graffiti")
    assert result.exit_code == 0
    same_results(native_out, out)
    assert yaml.safe_load((out / "config.yaml").read_text())["identity"]["imported"]["n_files"] == 10


def test_missing_and_bad_pairs_give_one_line_and_keep_what_was_imported(native, tmp_path):
    root, _, matches = native
    folder = tmp_path / "npz"
    for pair, m in matches.items():
        (folder / pair).parent.mkdir(parents=True, exist_ok=True)
        np.savez(folder / f"{pair}.npz", keypoints0=m.keypoints0, keypoints1=m.keypoints1)
    common = ["import", "hpatches", "--root", root, "--npz", folder, "--sequences", "v_boat", "--sequences", "v_graffiti"]
    (folder / "v_graffiti/1-4.npz").unlink()
    line = one_line_error(invoke(*common, "--out", tmp_path / "a"))
    assert "1 of 10 pairs are not in the source (first: v_graffiti/1-4, expected at" in line
    assert line.endswith("--skip-bad evaluates the others")
    result = invoke(*common, "--out", tmp_path / "b", "--skip-bad")
    assert result.exit_code == 0
    skipped = pd.read_csv(tmp_path / "b" / "skipped.csv")
    assert list(skipped["pair"]) == ["v_graffiti/1-4"]
    assert pd.read_csv(tmp_path / "b" / "summary.csv").iloc[0]["n_pairs"] == 9

    m = matches["v_graffiti/1-3"]
    bad = m.keypoints1.copy()
    bad[0] = np.nan
    np.savez(folder / "v_graffiti/1-3.npz", keypoints0=m.keypoints0, keypoints1=bad)
    np.savez(folder / "v_graffiti/1-4.npz", keypoints0=m.keypoints0, keypoints1=m.keypoints1)
    out = tmp_path / "c"
    line = one_line_error(invoke(*common, "--out", out))
    assert line.startswith("error: pair v_graffiti/1-3: keypoints1: 1 point(s) not finite")
    assert len(MatchCache(out / "matches.h5").names()) == 6  # v_boat's 5 and v_graffiti/1-2 stay

    np.savez(folder / "v_graffiti/1-3.npz", keypoints0=m.keypoints0 + [5000, 0], keypoints1=m.keypoints1)
    line = one_line_error(invoke(*common, "--out", out))
    assert "pair v_graffiti/1-3: keypoints0:" in line and "outside the 800x640 image" in line
    np.savez(folder / "v_graffiti/1-3.npz", keypoints0=m.keypoints0[:, :1], keypoints1=m.keypoints1)
    line = one_line_error(invoke(*common, "--out", out))
    assert "keypoints0 has shape" in line and "expected N x 2" in line
    assert len(MatchCache(out / "matches.h5").names()) == 6


def test_an_import_needs_exactly_one_readable_source(shared_data, tmp_path):
    root = shared_data / "hpatches-sequences-release"
    line = one_line_error(invoke("import", "hpatches", "--root", root, "--out", tmp_path / "o"))
    assert "give one source" in line
    (tmp_path / "f.h5").write_text("not hdf5")
    line = one_line_error(invoke("import", "hpatches", "--root", root, "--out", tmp_path / "o", "--hloc",
                                 tmp_path / "f.h5", tmp_path / "f.h5"))
    assert line.endswith("f.h5: not an HDF5 file")
