"""The house's rules that a reader of the code relies on (issue 71): typed data instead of keyed
side channels, one rule per default across sfm and reconstruct, the linter clean."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from e3cm_bench.sfm.protocol import ReconstructionProtocol, keypoints_are_detections

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "e3cm_bench"


def test_no_keyed_side_channel_in_the_package():
    """What a run reads of a pair is a typed field (its labels Pair.sequence/scene/category, its
    rotations, ViewPair.view0/view1/bag/setup, CorrespondencePair.corrs), not a `Pair.meta` key:
    a misspelt key is a silent default where it is read, a misspelt field an error where the
    pair is built. `.meta` is read nowhere in the package, neither subscripted nor by `.get`."""
    found = [f"{path.relative_to(REPO)}:{n}" for path in sorted(PACKAGE.rglob("*.py"))
             for n, line in enumerate(path.read_text().splitlines(), 1) if re.search(r"\.meta(\[|\.get\()", line)]
    assert not found, f"Pair.meta read: {found}"


def test_a_pairs_labels_are_typed_and_the_old_meta_still_builds_one():
    """`meta=` still builds a pair (code written against the dict), each key landing in its
    field; a key that names no label is refused where the pair is built; `pair.meta` is gone."""
    from e3cm_bench.datasets.base import Pair, stratum

    old = Pair("v_x/1-2", Path("a"), Path("b"), meta={"sequence": "v_x", "rot0": 1, "rot1": 3})
    assert (old.sequence, old.rotations, old.labels) == ("v_x", (1, 3), {"sequence": "v_x"})
    assert old == Pair("v_x/1-2", Path("a"), Path("b"), sequence="v_x", rotations=(1, 3))
    assert stratum(old) == ("v", "v_x")
    with pytest.raises(ValueError, match="unknown label.*sequnce"):
        Pair("p", Path("a"), Path("b"), meta={"sequnce": "v_x"})
    with pytest.raises(AttributeError, match="meta"):
        old.meta


@pytest.mark.parametrize("matcher, radius", [("sift", 0.0), ("aliked+lightglue", 0.0), ("e3cm", 2.0),
                                             ("xfeat-star", 2.0), ("loftr", 2.0)])
def test_reconstruct_merges_as_sfm_does(tmp_path, matcher, radius):
    """One rule for the merge default: reconstruct's folder resolves it as sfm's `--merge auto`
    does, from the matcher's keypoints_are_detections (reconstruct once merged by needs_backbone,
    which left xfeat-star's and LoFTR's semi-dense keypoints unmerged)."""
    from e3cm_bench.sfm.own_images import RECONSTRUCT
    from e3cm_bench.sfm.protocol import protocol_of

    detections = keypoints_are_detections(matcher)
    own = protocol_of(RECONSTRUCT.resolve_eval(None, 0, {})).resolved(detections)
    assert own.merge_px == ReconstructionProtocol().resolved(detections).merge_px == radius
    given = protocol_of(RECONSTRUCT.resolve_eval(None, 0, {"merge_px": 1.5})).resolved(detections)
    assert given.merge_px == 1.5  # a radius given is kept, for either kind


def test_pairs_of_a_folder_are_view_pairs(tmp_path):
    from e3cm_bench.sfm.own_images import FolderSetup, ImageFolder
    from e3cm_bench.sfm.views import ViewPair

    for k in range(3):
        cv2.imwrite(str(tmp_path / f"v{k}.png"), np.zeros((8, 8, 3), np.uint8))
    pairs = list(ImageFolder(tmp_path, camera_per_image=True))
    assert all(isinstance(p, ViewPair) and isinstance(p.setup, FolderSetup) for p in pairs)
    assert [(p.view0, p.view1) for p in pairs] == [("v0.png", "v1.png"), ("v0.png", "v2.png"), ("v1.png", "v2.png")]
    assert pairs[0].setup is pairs[1].setup and pairs[0].setup.camera_per_image
    # a record written before the option took its flag's name still loads
    assert ImageFolder(tmp_path, single_camera=False).reconstruction().camera_per_image


@pytest.mark.skipif(shutil.which("ruff") is None, reason="ruff is not installed (pip install -e '.[test]')")
def test_ruff_is_clean():
    """pyproject.toml's [tool.ruff]: what .ci/run checks, checked here too for a local run."""
    done = subprocess.run(["ruff", "check", "--no-cache", "."], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-1000:]


def test_every_module_a_comment_points_at_exists():
    """A comment or docstring that names one of the package's modules by path (`method/protocols.py`)
    names one that exists: five once pointed at modules that had moved. Another project's files are
    named with that project's folder first (`gluefactory/...`, `hloc/...`), which is none of ours."""
    ours = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    stale = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for named in re.findall(r"(?<![\w./])([a-z_]+/[a-z_/]*[a-z_]+\.py)\b", line):
                if named.split("/")[0] in ours and not (PACKAGE / named).exists():
                    stale.append(f"{path.relative_to(REPO)}:{n}: {named}")
    assert not stale, f"comments naming modules that do not exist: {stale}"
