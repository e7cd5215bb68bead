"""`e3cm-bench rank`: several matchers reconstruct one folder of real images (the shared KITTI frames,
their ground truth hidden), are ranked without ground truth into OUT/verdict.csv and OUT/index.html;
a failing matcher is recorded and the others go on; an interrupted rank resumes to the same verdict;
the runs read as any reconstruct run's."""

from __future__ import annotations

import shutil
from pathlib import Path

import pandas as pd
import pytest

from helpers import invoke

pytest.importorskip("pycolmap")
pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
LADDER = REPO / "scripts" / "validate"
KITTI = "megadepth_test_1500/Undistorted_SfM/kitti00/images"
MATCHERS = "sift,ladder:noise_1px,ladder:noise_4px,broken:factory"
# What a rank's verdict holds that does not depend on the machine (the cost columns do).
STABLE = ["rank", "method", "score", "score_lo", "score_hi", "vs_next", "registered_images", "points", "failed"]
BROKEN = '''
import e3cm_bench as eb


class Broken(eb.Matcher):
    name = "broken"

    def match(self, image0, image1):
        raise RuntimeError("this matcher always fails")


def factory():
    return Broken()
'''


@pytest.fixture(scope="module")
def frames(shared_data, tmp_path_factory) -> Path:
    """The first 8 KITTI frames, alone in a folder of one's own (no scene_info: no ground truth)."""
    folder = tmp_path_factory.mktemp("frames")
    for path in sorted((shared_data / KITTI).iterdir())[:8]:
        shutil.copy(path, folder / path.name)
    return folder


@pytest.fixture(scope="module")
def modules(tmp_path_factory) -> Path:
    """A folder with the ladder (scripts/validate/ladder.py) and a matcher that always fails."""
    folder = tmp_path_factory.mktemp("modules")
    shutil.copy(LADDER / "ladder.py", folder / "ladder.py")
    (folder / "broken.py").write_text(BROKEN)
    return folder


def rank(frames: Path, out: Path, modules: Path, monkeypatch):
    monkeypatch.chdir(modules)  # module:factory names are found in the current folder
    return invoke("rank", frames, "--out", out, "--matchers", MATCHERS, "--window", "2", env={"COLUMNS": "200"})


@pytest.fixture(scope="module")
def ranked(frames, modules, tmp_path_factory):
    out = tmp_path_factory.mktemp("rank") / "out"
    with pytest.MonkeyPatch.context() as monkeypatch:
        result = rank(frames, out, modules, monkeypatch)
    return out, result


def test_a_folder_is_ranked_and_a_failing_matcher_recorded(ranked):
    out, result = ranked
    assert result.exit_code == 0, result.output
    table = pd.read_csv(out / "verdict.csv")
    assert list(table["method"])[2:] == ["ladder-noise_4px", "broken-factory"]  # the most degraded last
    assert list(table["rank"].iloc[:3]) == [1, 2, 3] and pd.isna(table["rank"].iloc[3])
    assert "this matcher always fails" in table["failed"].iloc[3] and "broken-factory failed" in result.output
    ok = table.iloc[:3]
    assert (ok["score_lo"] <= ok["score"]).all() and (ok["score"] <= ok["score_hi"]).all()
    assert (ok["seconds_per_image"] > 0).all() and (ok["n_pairs_scored"] > 0).all()
    assert table["vs_next"].iloc[0] in ("better than the next", "no difference detectable")
    page = (out / "index.html").read_text()
    assert "ladder-noise_4px" in page and (out / "cost_score.png").is_file()
    assert sorted(p.name for p in (out / "drawings" / "sift").iterdir()) == ["pair0.jpg", "pair1.jpg"]
    record = (out / "rank.yaml").read_text()
    assert "geometric median" in record and "broken:factory" in record


def test_an_interrupted_rank_resumes_to_the_same_verdict(ranked, frames, modules, tmp_path, monkeypatch):
    import e3cm_bench.apps.rank as app

    out = tmp_path / "out"
    real, calls = app.run_one, []

    def interrupted(request, matcher, console):
        calls.append(matcher)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C during the second matcher's run
        return real(request, matcher, console)

    monkeypatch.setattr(app, "run_one", interrupted)
    assert rank(frames, out, modules, monkeypatch).exit_code != 0
    assert not (out / "verdict.csv").exists() and (out / "runs" / "sift").is_dir()
    monkeypatch.setattr(app, "run_one", real)
    assert rank(frames, out, modules, monkeypatch).exit_code == 0
    again, whole = pd.read_csv(out / "verdict.csv"), pd.read_csv(ranked[0] / "verdict.csv")
    pd.testing.assert_frame_equal(again[STABLE], whole[STABLE])


def test_its_runs_read_as_reconstruct_runs(ranked, tmp_path):
    out, _ = ranked
    runs = [out / "runs" / "sift", out / "runs" / "ladder-noise_1px"]
    table = invoke("table", *runs, "--out", tmp_path / "t", "--no-paper")
    assert table.exit_code == 0, table.output
    report = invoke("report", *runs, "--out", tmp_path / "report")
    assert report.exit_code == 0 and (tmp_path / "report" / "index.html").is_file(), report.output
