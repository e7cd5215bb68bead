"""What a plugin's match() may return (issue 70, item 5): NaN, inf, points outside the image,
the wrong types, None, more matches than pixels: each ends the pair in one line naming the
matcher and the problem, and the pairs matched before stay in the cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from e3cm_bench.ground.matches import Matches
from e3cm_bench.matchers import MatcherEntry, register, unregister
from e3cm_bench.storage.cache import MatchCache
from helpers import invoke, one_line_error


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile-returns")
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


def _good(image0, image1):
    k = np.array([[10.0, 10.0], [20.0, 30.0], [40.0, 15.0], [25.0, 25.0]])
    return Matches(k, k + 1, np.ones(4))


def _nan(image0, image1):
    m = _good(image0, image1)
    m.keypoints0[1, 0] = np.nan
    return m


def _inf(image0, image1):
    m = _good(image0, image1)
    m.keypoints1[2, 1] = np.inf
    return m


def _outside(image0, image1):
    m = _good(image0, image1)
    m.keypoints0[0] = (image0.shape[1] + 50.0, 3.0)
    return m


def _strings(image0, image1):
    m = _good(image0, image1)
    m.keypoints0 = [["a", "b"]] * 4
    return m


def _too_many(image0, image1):
    n = image0.shape[0] * image0.shape[1] + 1
    k = np.zeros((n, 2), np.float32)
    return Matches(k, k, np.ones(n, np.float32))


CASES = {
    "nan": (_nan, "point(s) not finite"),
    "inf": (_inf, "point(s) not finite"),
    "outside": (_outside, "outside the"),
    "strings": (_strings, "not numbers"),
    "none": (lambda image0, image1: None, "returned NoneType, expected e3cm_bench.Matches"),
    "tuple": (lambda image0, image1: (np.zeros((3, 2)), np.zeros((3, 2))), "returned tuple"),
    "too-many": (_too_many, "more than the"),
}


class Hostile:
    """Good matches on the first pair, then `bad` on the second."""

    keypoints_in_image = True

    def __init__(self, bad):
        self.bad, self.calls, self.name = bad, 0, "hostile"

    def match(self, image0, image1):
        self.calls += 1
        return _good(image0, image1) if self.calls == 1 else self.bad(image0, image1)

    def config(self):
        return {"matcher": self.name}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_bad_return_fails_its_pair_in_one_line_and_keeps_the_first(boat, tmp_path, case):
    bad, says = CASES[case]
    register(MatcherEntry("hostile", "returns bad matches on its second pair", build=lambda s: Hostile(bad), origin="test"))
    try:
        out = tmp_path / "run"
        line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", "hostile", "--max-side", 240))
        assert line.startswith("error: pair v_boat/1-3: matcher hostile") and says in line, line
        assert MatchCache(out / "matches.h5").names() == ["v_boat/1-2"]
        skipped = invoke("hpatches", "--root", boat, "--out", out, "--matcher", "hostile", "--max-side", 240,
                         "--on-matcher-error", "fail-pair")
        assert skipped.exit_code == 0, skipped.output  # the bad pairs counted as failed, the run finished
    finally:
        unregister("hostile")
