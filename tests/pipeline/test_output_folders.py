"""Where commands write: a report that replaces only its own folder, no output
written through a symbolic link, no code imported from a run folder, experiment labels kept
inside --out, and the report page's data block safe from any name.

Each command-level test works on copies of a small SIFT run on one HPatches sequence.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

from e3cm_bench.ground import files
from e3cm_bench.reporting.site import MARKER, script_json
from helpers import invoke, one_line_error


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    """An HPatches root with the one sequence v_boat."""
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


@pytest.fixture(scope="module")
def made_run(boat, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("made") / "sift"
    result = invoke("hpatches", "--root", boat, "--out", out, "--matcher", "sift", "--limit", 2, "--max-side", 320)
    assert result.exit_code == 0
    return out


def run_copy(made_run: Path, folder: Path, label: str | None = None, matcher: str | None = None) -> Path:
    """A copy of the SIFT run at `folder`, its config's label and identity.matcher changed if given."""
    shutil.copytree(made_run, folder)
    config = yaml.safe_load((folder / "config.yaml").read_text())
    if label is not None:
        config["method"] = label
    if matcher is not None:
        config["identity"]["matcher"] = matcher
    (folder / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return folder


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (relative path -> content), links as 'link -> target'."""
    found = {}
    for path in sorted(folder.rglob("*")):
        if path.is_symlink():
            found[path.relative_to(folder).as_posix()] = f"link -> {os.readlink(path)}".encode()
        elif path.is_file():
            found[path.relative_to(folder).as_posix()] = path.read_bytes()
    return found


def leftovers(folder: Path) -> list[str]:
    """Temporary folders of a report left beside its target."""
    return sorted(p.name for p in folder.iterdir() if ".report-" in p.name)


# ----------------------------------------------------------------------------- 1. report --out


def test_a_report_into_a_folder_of_runs_is_refused_and_deletes_nothing(made_run, tmp_path, monkeypatch):
    project = tmp_path / "proj"
    run_copy(made_run, project / "runs" / "sift", "sift")
    run_copy(made_run, project / "runs" / "sift2", "sift2")
    (project / "img").mkdir()
    (project / "img" / "holiday.jpg").write_bytes(b"\xff\xd8 a photo")
    before = tree(project)
    monkeypatch.chdir(project)
    line = one_line_error(invoke("report", "runs/sift", "runs/sift2", "--out", "."))
    assert str(project) in line and "not a report folder" in line
    assert tree(project) == before
    assert leftovers(project.parent) == [] and leftovers(project) == []


def test_a_users_photo_under_out_survives(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    site = tmp_path / "site"
    (site / "img").mkdir(parents=True)
    (site / "img" / "holiday.jpg").write_bytes(b"\xff\xd8 a photo")
    line = one_line_error(invoke("report", run, "--out", site))
    assert str(site) in line and "img" in line
    assert tree(site) == {"img/holiday.jpg": b"\xff\xd8 a photo"}
    # a file put into a previous report (marker and all) is not the report's either
    good = tmp_path / "good"
    assert invoke("report", run, "--out", good).exit_code == 0
    (good / "notes.txt").write_text("mine")
    line = one_line_error(invoke("report", run, "--out", good))
    assert str(good) in line and "notes.txt" in line
    assert (good / "notes.txt").read_text() == "mine"


def test_a_second_report_replaces_the_first_whole(made_run, tmp_path):
    a = run_copy(made_run, tmp_path / "a", "a")
    b = run_copy(made_run, tmp_path / "b", "b")
    site = tmp_path / "site"
    assert invoke("report", a, b, "--out", site, "--no-compare").exit_code == 0
    assert (site / MARKER).is_file() and (site / "runs" / "02" / "summary.csv").is_file()
    result = invoke("report", b, "--out", site, "--no-compare")
    assert result.exit_code == 0
    # replaced, not merged: the second run's folder of the first report is gone
    assert (site / MARKER).is_file() and not (site / "runs" / "02").exists()
    assert ">b<" in (site / "index.html").read_text() and "<b>a</b>" not in (site / "index.html").read_text()
    assert leftovers(tmp_path) == []


def test_an_empty_folder_is_filled_in_place(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    site = tmp_path / "site"
    site.mkdir()
    inode = site.stat().st_ino
    assert invoke("report", run, "--out", site).exit_code == 0
    assert site.stat().st_ino == inode  # a shell standing in it still sees the report
    assert (site / "index.html").is_file() and (site / MARKER).is_file()


def test_a_report_that_fails_midway_keeps_the_previous_one(made_run, tmp_path):
    good = run_copy(made_run, tmp_path / "good", "good")
    # mathtext that matplotlib cannot parse: the comparison plot raises once the report is under way
    bad = run_copy(made_run, tmp_path / "bad", r"$\frac{$")
    site = tmp_path / "site"
    assert invoke("report", good, "--out", site).exit_code == 0
    before = tree(site)
    assert len(before) > 5
    result = invoke("report", bad, "--out", site)
    assert result.exit_code == 2, result.output
    assert tree(site) == before
    assert leftovers(tmp_path) == []


def test_sigterm_during_a_report_keeps_the_previous_one(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    site = tmp_path / "site"
    assert invoke("report", run, "--out", site).exit_code == 0
    before = tree(site)
    parked = tmp_path / "parked"
    # The real command, held in the middle of its drawings until a signal ends it.
    script = textwrap.dedent(f"""
        import sys, time
        from pathlib import Path
        import e3cm_bench.reporting.site as reportsite
        def park(*args, **kwargs):
            Path({str(parked)!r}).write_text("here")
            while True:
                time.sleep(0.05)
        reportsite.draw_pairs = park  # site.py calls it by this name (drawings.py)
        from e3cm_bench.cli import app
        sys.argv = ["e3cm-bench", "report", {str(run)!r}, "--out", {str(site)!r}]
        app()
    """)
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not parked.exists():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert leftovers(tmp_path)  # the new report is being built beside the old one
    process.send_signal(signal.SIGTERM)
    process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGTERM
    assert tree(site) == before
    assert leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- 2. symbolic links


def test_the_writers_refuse_or_replace_links_and_never_write_through_them(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    link = tmp_path / "out.csv"
    link.symlink_to(victim)
    with pytest.raises(ValueError, match=r"out\.csv: is a symbolic link"):
        files.write_csv(pd.DataFrame({"a": [1]}), link)
    with pytest.raises(ValueError, match=r"out\.csv: is a symbolic link"):
        files.create_new(link)
    dangling = tmp_path / "new.yaml"
    dangling.symlink_to(tmp_path / "created.txt")
    with pytest.raises(ValueError, match=r"new\.yaml: is a symbolic link"):
        files.save_yaml({"a": 1}, dangling)
    with pytest.raises(ValueError, match="already exists"):
        files.create_new(victim)
    assert victim.read_text() == "precious" and not (tmp_path / "created.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.yaml", "out.csv", "victim.txt"]  # no temporaries


@pytest.mark.parametrize("dangling", [False, True])
def test_a_lock_that_is_a_link_is_refused(boat, tmp_path, dangling):
    victim = tmp_path / ("missing.txt" if dangling else "victim.txt")
    if not dangling:
        victim.write_text("precious")
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").symlink_to(victim)
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", "sift", "--limit", 1,
                                 "--max-side", 320))
    assert str(out / ".lock") in line and "symbolic link" in line
    assert (not victim.exists()) if dangling else victim.read_text() == "precious"


def test_a_lock_with_another_name_is_refused(boat, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "run"
    out.mkdir()
    os.link(victim, out / ".lock")
    line = one_line_error(invoke("hpatches", "--root", boat, "--out", out, "--matcher", "sift", "--limit", 1,
                                 "--max-side", 320))
    assert str(out / ".lock") in line and "hard links" in line
    assert victim.read_text() == "precious"


def test_match_does_not_write_its_npz_through_a_link(boat, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "m"
    out.mkdir()
    (out / "matches.npz").symlink_to(victim)
    images = sorted((boat / "v_boat").glob("*.ppm"))[:2]
    line = one_line_error(invoke("match", *images, "--matcher", "sift", "--max-side", 320, "--out", out))
    assert str(out / "matches.npz") in line and "symbolic link" in line
    assert victim.read_text() == "precious"


def test_report_does_not_write_its_index_through_a_link(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    site = tmp_path / "site"
    assert invoke("report", run, "--out", site).exit_code == 0
    (site / "index.html").unlink()
    (site / "index.html").symlink_to(victim)
    assert invoke("report", run, "--out", site).exit_code == 0  # its own folder: replaced, link and all
    assert victim.read_text() == "precious"
    assert not (site / "index.html").is_symlink() and "e3cm-bench report" in (site / "index.html").read_text()
    # a folder it did not write, holding such a link, is refused
    other = tmp_path / "other"
    other.mkdir()
    (other / "index.html").symlink_to(victim)
    line = one_line_error(invoke("report", run, "--out", other))
    assert str(other) in line
    assert victim.read_text() == "precious"


# ----------------------------------------------------------------------------- 3. no code from data


def test_a_run_folders_matcher_is_never_imported(made_run, tmp_path):
    folders = [run_copy(made_run, tmp_path / name.replace(":", "_"), name, matcher=name)
               for name in ("this:x", "os:abort", "signal:pause")]
    # One process runs table and report on each; importing `this` prints the Zen of Python,
    # os:abort ends the process (134), signal:pause hangs it (the timeout).
    script = textwrap.dedent(f"""
        import sys
        from typer.testing import CliRunner
        from e3cm_bench.cli import app
        for folder in {[str(f) for f in folders]!r}:
            for args in (["table", folder, "--out", folder + "-table"], ["report", folder, "--out", folder + "-site"]):
                result = CliRunner().invoke(app, args)
                assert result.exit_code == 0, (args, result.output)
                assert "Beautiful is better" not in result.output
        assert "this" not in sys.modules
        print("imported nothing")
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("imported nothing") and "Beautiful is better" not in done.stdout


def test_the_registry_imports_a_module_only_when_asked(monkeypatch):
    from e3cm_bench.matchers import get_matcher

    monkeypatch.delitem(sys.modules, "this", raising=False)
    with pytest.raises(ValueError, match="imported only when named by --matcher"):
        get_matcher("this:x")
    assert "this" not in sys.modules


# ----------------------------------------------------------------------------- 6. experiment labels


@pytest.mark.parametrize("label", ["../../x", "/an/absolute/path", ".."])
def test_an_experiment_label_that_is_a_path_is_refused(boat, tmp_path, label):
    config = tmp_path / "exp.yaml"
    config.write_text(yaml.safe_dump({"benchmark": "hpatches", "methods": [{"matcher": "sift", "label": label}]}))
    out = tmp_path / "a" / "b" / "out"
    line = one_line_error(invoke("reproduce", config, "--root", boat, "--out", out, "--limit", 1, "--max-side", 320))
    assert str(config) in line and repr(label) in line
    assert not (tmp_path / "a").exists() and not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- 12a. the page's data


def test_script_json_holds_no_markup_and_round_trips():
    data = {"names": ["v_<!--<script>", "</script><b>", "a&b", "x>y"]}
    text = script_json(data)
    assert "<" not in text and ">" not in text and "&" not in text
    assert json.loads(text) == data


def test_the_pages_data_survives_a_sequence_named_like_markup(made_run, tmp_path):
    run = run_copy(made_run, tmp_path / "sift")
    per_pair = pd.read_csv(run / "per_pair.csv")
    name = "v_<!--<script>/1-2"
    per_pair.loc[0, "pair"] = name
    per_pair.to_csv(run / "per_pair.csv", index=False)
    site = tmp_path / "site"
    assert invoke("report", run, "--out", site).exit_code == 0
    page = (site / "index.html").read_text()
    # The data block ends at the first </script>, as a browser ends it; with no '<' inside it no
    # name can open a comment or a script state that would carry the block past its end.
    block = re.search(r'<script type="application/json" id="pair-data">(.*?)</script>', page, re.S).group(1)
    assert "<" not in block
    data = json.loads(block)
    assert [p["pair"] for p in data["pairs"]] == list(per_pair["pair"])
    assert page.count("<script") == 2 and page.rstrip().endswith("</body></html>")
