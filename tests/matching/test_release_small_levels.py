"""The released E3CM cascade where a level keeps exactly 7 matches or holds fewer than 8.

With 7 points, OpenCV's findFundamentalMat (FM_RANSAC) runs its 7-point algorithm alone and
returns every real solution stacked (9x3 for three); the release filters the next level with
the first (its outlier_rejection takes the first three rows of any F that is not 3x3). A
level with fewer than 8 matches is skipped and the F before it filters the next level.

The references in tests/data/parity were made by the release's own code (match_large_img and
utils.refinement_pose_ransac, unmodified, cv2.setRNGSeed(0), seed-0 VGG19) on crops of
../shared/parity's graf12_640 (tests/data/parity/manifest.json), in the layout of
../shared/parity. These tests need neither the weights nor ../shared: they run the released
cascade on the reference's own per-level lists, where every survivor and F must be exact.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO_ROOT

DATA = REPO_ROOT / "tests" / "data" / "parity"
SEVEN = "graf12_640_c160x224"  # level 2 keeps 7 matches: F2 is 9x3 and filters level 1
SKIPPED = "graf12_640_c128x256"  # level 3 keeps 7 (F3 9x3); levels 2 and 1 hold 7 each: F3 filters level 0
TAG = "r095"


def load(name: str) -> dict:
    return dict(np.load(DATA / f"{name}.npz"))


def survivors_under_each_solution(ref: dict, f_level: int, level: int) -> list[bool]:
    """For each stacked solution of the reference's F at `f_level`: does filtering `level`'s
    list with it (the release's residual test) give the reference's survivors there?"""
    from e3cm_bench.matching.release import ReleaseCascade, algebraic_residual

    stacked = ref[f"{TAG}_F{f_level}"]
    x0, x1 = ref[f"{TAG}_L{level}_A"], ref[f"{TAG}_L{level}_B"]
    same = []
    for k in range(len(stacked) // 3):
        keep = np.abs(algebraic_residual(stacked[3 * k:3 * k + 3], x0, x1)) < ReleaseCascade().residual
        same.append(np.array_equal(x0[keep], ref[f"{TAG}_cascL{level}_A"])
                    and np.array_equal(x1[keep], ref[f"{TAG}_cascL{level}_B"]))
    return same


@pytest.mark.parametrize("name", (SEVEN, SKIPPED))
def test_released_cascade_equals_the_releases_survivors_and_F(name):
    """Every level's survivors, the result and every F (the stacked one by the solution the
    release used) are the release's exactly; an F on one side only would be another cascade."""
    from parity import fundamental_differences, fundamental_mismatches, release_cascade_from_reference

    ref = load(name)
    checks, out = release_cascade_from_reference(ref, TAG)
    for check in checks:
        assert check.n_both == check.n_ref == check.n_ours, check.line()
    assert {4 - i for i in out["survivors"]} == {level for level in range(4) if f"{TAG}_cascL{level}_A" in ref}
    assert fundamental_mismatches(out, ref, TAG) == []
    assert set(fundamental_differences(out, ref, TAG).values()) == {0.0}


def test_seven_survivors_give_three_stacked_solutions_and_the_first_filters_the_next_level():
    from parity import release_cascade_from_reference

    ref = load(SEVEN)
    assert len(ref[f"{TAG}_cascL2_A"]) == 7 and ref[f"{TAG}_F2"].shape == (9, 3)
    _, out = release_cascade_from_reference(ref, TAG)
    assert out["solutions"] == {2: 3}  # list 2 = level 2
    np.testing.assert_array_equal(out["fundamentals"][2], ref[f"{TAG}_F2"][:3])
    assert "7-point" in out["notes"][2]
    # Only the first solution gives the release's level-1 survivors: another choice fails here.
    assert survivors_under_each_solution(ref, 2, 1) == [True, False, False]
    assert len(out["survivors"][3][0]) == len(ref[f"{TAG}_cascL1_A"]) == 17


def test_levels_with_fewer_than_8_matches_are_skipped_and_the_stacked_F_above_filters_level_0():
    from parity import release_cascade_from_reference

    ref = load(SKIPPED)
    assert [len(ref[f"{TAG}_L{level}_A"]) for level in (2, 1)] == [7, 7]
    assert ref[f"{TAG}_F3"].shape == (9, 3) and f"{TAG}_F2" not in ref and f"{TAG}_F1" not in ref
    _, out = release_cascade_from_reference(ref, TAG)
    assert sorted(out["survivors"]) == [1, 4]  # levels 3 and 0 filtered, 2 and 1 skipped
    assert "fewer than 8" in out["notes"][2] and "fewer than 8" in out["notes"][3]
    assert out["solutions"] == {1: 3}
    # Level 0 is filtered by F3's first solution (the second would keep another set), so
    # the result is not the unfiltered level 0 that a cascade stopping at level 2 returns.
    assert survivors_under_each_solution(ref, 3, 0)[:2] == [True, False]
    assert len(out["points0"]) == len(ref[f"{TAG}_casc_A"]) == 6 < len(ref[f"{TAG}_L0_A"]) == 8
    assert out["fundamentals"][4] is None and "no F from 6" in out["notes"][4]  # 6 survivors: OpenCV finds none


def test_a_reference_F_of_an_unknown_shape_is_named_with_its_shape():
    from parity import check_reference, fundamental_differences, release_cascade_from_reference

    ref = load(SEVEN)
    _, out = release_cascade_from_reference(ref, TAG)
    bad = {**ref, f"{TAG}_F2": ref[f"{TAG}_F2"][:2]}
    for call in (lambda: fundamental_differences(out, bad, TAG), lambda: check_reference(bad)):
        with pytest.raises(ValueError, match=f"^{TAG}_F2: shape 2x3, "):
            call()
    check_reference(ref)  # 9x3 is read


def test_parity_script_names_a_2x3_reference_F_in_one_line(tmp_path):
    """The script reads the reference before any image or weights: an F it cannot read ends
    the run with exit status 2 and one line naming the key and its shape, no traceback."""
    ref = load(SEVEN)
    bad = tmp_path / "bad.npz"
    np.savez(bad, **{**ref, f"{TAG}_F2": ref[f"{TAG}_F2"][:2]})
    missing = str(tmp_path / "absent")
    run = subprocess.run([sys.executable, str(REPO_ROOT / "scripts" / "maintain" / "check_parity.py"), str(bad), missing + ".png",
                          missing + ".png", "--weights", missing + ".pth"], capture_output=True, text=True, timeout=300)
    lines = (run.stdout + run.stderr).strip().splitlines()
    assert run.returncode == 2, run.stdout + run.stderr
    assert len(lines) == 1 and lines[0] == f"{bad}: {TAG}_F2: shape 2x3, not a fundamental matrix (3x3) nor OpenCV's " \
                                           f"stacked 7-point solutions (6x3, 9x3)", lines
