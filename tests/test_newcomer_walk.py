"""The first hour of a new user, as a test: the README's Quickstart and tour, and the
docs' tutorial blocks that run offline, read from the files (so an edit of them is tested),
run one after the other through the installed `e3cm-bench` command in a fresh folder, on the
shared data samples, with stdout a pipe (as in CI or `| less`).

A step fails the walk when it exits non-zero the first time, when its output holds a
traceback, or (compare, table, check) when a line of its stdout is wider than 80 columns.

Bounded to stay within a few minutes on a 2-core machine: every command that matches gets
`--limit 2` on small images (and the demo `--quick` with two methods), as `bounded` says, and
the steps that need the network (downloads, the peers' weights) or scale out (tests/pipeline/test_shards.py
covers those) are left out, each with its reason in SKIPPED.

Beside the walk, what a newcomer meets next: an editable plugin edited between two runs, a
mistyped `--matcher sfit` (did you mean sift), and a busy folder refused before torch loads.
"""

from __future__ import annotations

import glob
import os
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
WIDTH = 80
NARROW = ("compare", "table", "check")  # the commands whose output must read at 80 columns

# What the tour's placeholders stand for on the shared samples.
IMAGES = {"a.jpg": "hpatches-sequences-release/v_boat/1.ppm", "b.jpg": "hpatches-sequences-release/v_boat/2.ppm",
          "photos/": "megadepth_test_1500/Undistorted_SfM/kitti00/images"}  # 20 frames, no ground truth given
ROOTS = {"hpatches": "hpatches-sequences-release", "wxbs": "WxBS", "evd": "EVD", "table1": "hpatches-sequences-release"}
SMALL = {"hpatches": ["--sequences", "v_boat", "--limit", "2", "--max-side", "320"],
         "wxbs": ["--limit", "2", "--max-side", "320"], "evd": ["--limit", "2", "--max-side", "320"]}
# rank runs as the tour gives it, at full size (under 2 min on 2 cores): at 640 px xfeat's matches on
# the 376-px-high KITTI frames hold no model together (0 of 20 registered, by either mapper)


def blocks(path: Path, sections: tuple[str, ...] | None = None) -> list[str]:
    """The ```bash blocks of a Markdown file (of the `## ` sections named, if given)."""
    found, section = [], None
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("## "):
            section = line[3:].strip()
        if line.strip() == "```bash" and (sections is None or section in sections):
            j = lines.index("```", i + 1)
            found.append("\n".join(lines[i + 1:j]))
            i = j
        i += 1
    return found


def commands(block: str) -> list[list[str]]:
    """Each `e3cm-bench` command of a block as its words: continuation lines joined, comments
    and the synopsis' optional `[...]` parts dropped."""
    out = []
    for line in block.replace("\\\n", " ").splitlines():
        for part in line.split("&&"):
            words = shlex.split(part, comments=True)
            if not words or words[0] != "e3cm-bench":
                continue
            kept, depth = [], 0
            for word in words[1:]:
                depth += word.count("[") if word.startswith("[") else 0
                if depth == 0:
                    kept.append(word)
                depth -= word.count("]") if depth and word.endswith("]") else 0
            out.append(kept)
    return out


# Steps left out of the walk, by a word they hold, and why.
SKIPPED = {
    "download": "needs the network (tests/download/test_download*.py serve the files locally)",
    "loftr": "the peers download their weights (tests/matching/test_peers.py)",
    "--workers": "scale-out: tests/pipeline/test_shards.py", "--shard": "scale-out: tests/pipeline/test_shards.py",
    "--launcher": "scale-out: tests/pipeline/test_shards.py", "scripts/results/wxbs_evd_tables.py": "a script, not a command",
}


def bounded(words: list[str]) -> list[str] | None:
    """A step as the walk runs it: placeholders made real, --root given where the data is the
    shared sample's, and small (see the module docstring); None: the data is not here."""
    words = [str(SHARED / IMAGES[w]) if w in IMAGES else w for w in words]
    command = words[0]
    target = words[1] if command in ("import", "reproduce") and len(words) > 1 else command
    if "--root" in words:
        at = words.index("--root") + 1
        given = words[at]
        if given.startswith("data/"):  # the downloaded layout: the shared copy of it
            words[at] = str(SHARED / given.removeprefix("data/"))
        if not Path(words[at]).exists() and not given.startswith("runs/"):
            return None
    elif target in ROOTS:
        words += ["--root", str(SHARED / ROOTS[target])]
    small = SMALL.get("hpatches" if target == "table1" else target, [])
    for flag, value in zip(small[::2], small[1::2]):
        if flag not in words and not (command == "import" and flag == "--max-side"):  # import matches nothing
            words += [flag, value]
    if command == "reproduce":
        words += ["--methods", "sift,e3cm"]
    if command == "demo":
        words += ["--quick", "--methods", "sift,e3cm"]
    if words[:2] == ["synth", "stereo"]:
        words = set_option(words, "--frames", "2")
    if command == "calibrate":
        words += ["--frames", "1", "--frames", "2", "--max-side", "160"]
    expanded = []
    for word in words:  # the shell's glob (report runs/table1/*), in the walk's folder
        expanded += sorted(glob.glob(word)) if "*" in word and glob.glob(word) else [word]
    return expanded


def set_option(words: list[str], flag: str, value: str) -> list[str]:
    if flag in words:
        at = words.index(flag) + 1
        return words[:at] + [value] + words[at + 1:]
    return words + [flag, value]


@dataclass
class Step:
    source: str
    words: list[str]
    code: int
    stdout: str
    stderr: str
    cwd: Path | None = None


def walk_plan() -> list[tuple[str, list[str]]]:
    """(where, words) of every step, in the order a reader meets them."""
    plan = []
    readme = REPO / "README.md"
    for block in blocks(readme, ("Quickstart", "A tour of the commands")):
        plan += [("README.md", words) for words in commands(block)]
    for page in ("wxbs-evd.md", "calibration.md"):
        plan += [(f"docs/{page}", words) for words in commands(blocks(REPO / "docs" / page)[0])]
    return plan


def entry_point() -> str | None:
    beside = Path(sys.executable).parent / "e3cm-bench"
    return str(beside) if beside.exists() else shutil.which("e3cm-bench")


@pytest.fixture(scope="module")
def walk(shared_data, tmp_path_factory) -> list[Step]:
    entry = entry_point()
    if entry is None:
        pytest.skip("the e3cm-bench command is not installed (pip install -e .)")
    folder = tmp_path_factory.mktemp("newcomer")
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "E3CM_BENCH_DEBUG")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    env["E3CM_BENCH_DATA"] = str(folder / "data")  # nothing downloaded: the steps name --root
    steps = []
    cwd = Path.cwd()
    try:
        for source, words in walk_plan():
            here = folder / source.replace("/", "-")  # each file's walk in a folder of its own
            here.mkdir(exist_ok=True)
            os.chdir(here)  # the glob of `report runs/table1/*` is the walk's
            skip = next((why for word, why in SKIPPED.items() if word in words), None)
            run = None if skip else bounded(words)
            if run is None:
                print(f"skipped ({skip or 'its data is not in ../shared/data'}): e3cm-bench {' '.join(words)}")
                continue
            start = time.perf_counter()
            done = subprocess.run([entry, *run], cwd=here, env=env, capture_output=True, text=True, timeout=900)
            print(f"$ e3cm-bench {' '.join(run)}    [{source}; {time.perf_counter() - start:.1f} s]")
            print(done.stdout + done.stderr)
            steps.append(Step(source, run, done.returncode, done.stdout, done.stderr, here))
    finally:
        os.chdir(cwd)
    return steps


def test_the_walk_reads_the_files():
    plan = walk_plan()
    names = [words[0] for _, words in plan]
    for command in ("demo", "match", "hpatches", "compare", "table", "reproduce", "import", "report", "check",
                    "calibrate", "wxbs", "evd", "reconstruct"):
        assert command in names, (command, names)
    # the tour's steps that match with a deep matcher run offline as written
    deep = [words for where, words in plan if where == "README.md" and words[0] in ("match", "reproduce", "hpatches")
            and "sift" not in words and "--workers" not in words]
    assert deep and all("--backbone" in words and "efficientnet_lite0" in words for words in deep), deep


@pytest.mark.slow  # the walk's steps
def test_the_tour_writes_a_latex_table_and_pdf_plots(walk):
    step = next(s for s in walk if s.words[0] == "table" and "--latex" in s.words)
    assert step.code == 0 and "tables/mine.tex" in step.stdout, step.stdout + step.stderr
    assert "SIFT+NN" not in step.stdout  # --no-paper: the runs' rows only


@pytest.mark.slow  # the walk runs every step once: about a minute
def test_every_step_works_the_first_time(walk):
    failed = [f"e3cm-bench {' '.join(s.words)} [{s.source}] exit {s.code}: {s.stderr.strip()[-300:]}"
              for s in walk if s.code != 0]
    assert len(walk) >= 15 and not failed, "\n".join(failed)


@pytest.mark.slow  # the walk runs every step once: about a minute
def test_no_step_prints_a_traceback(walk):
    assert not [s.words for s in walk if "Traceback" in s.stdout + s.stderr]


@pytest.mark.slow  # the walk runs every step once: about a minute
def test_compare_table_and_check_read_at_80_columns(walk):
    """Their tables within 80 columns in a pipe; a message (a verdict, the files written) one whole line."""
    from helpers import table_lines

    narrow = [s for s in walk if s.words[0] in NARROW]
    assert {s.words[0] for s in narrow} == set(NARROW)
    wide = [f"{s.words[0]}: {len(line)} columns: {line!r}" for s in narrow for line in table_lines(s.stdout)
            if len(line) > WIDTH]
    assert not wide, "\n".join(wide)
    assert all("…" not in s.stdout for s in narrow)


@pytest.mark.slow  # the walk runs every step once
def test_reconstruct_makes_a_model_of_the_kitti_frames_without_ground_truth(walk):
    """The tour's `reconstruct photos/ ... --matcher sift --window 2`, on the 20 shared KITTI frames."""
    pycolmap = pytest.importorskip("pycolmap")
    import pandas as pd

    step = next(s for s in walk if s.words[0] == "reconstruct")
    assert step.code == 0 and "--window" in step.words and "sift" in step.words
    out = step.cwd / step.words[step.words.index("--out") + 1]
    summary = pd.read_csv(out / "summary.csv").iloc[0]
    assert summary["n_images"] == 20 and summary["largest_model_images"] >= 15, summary.to_dict()
    model = pycolmap.Reconstruction(str(out / "sparse" / "0"))  # what COLMAP's GUI and hloc read
    assert model.num_reg_images() == summary["largest_model_images"]


@pytest.mark.slow  # the walk runs every step once
def test_rank_ranks_the_tours_matchers_on_the_kitti_frames_without_ground_truth(walk):
    """The tour's `rank photos/ --matchers sift,xfeat,e3cm-plus ...` on the 20 shared KITTI frames:
    every matcher ranked, each with its interval and its cost, and the page written."""
    import pandas as pd

    step = next(s for s in walk if s.words[0] == "rank")
    assert step.code == 0 and "verdict.csv" in step.stdout, step.stdout + step.stderr
    out = step.cwd / step.words[step.words.index("--out") + 1]
    table = pd.read_csv(out / "verdict.csv")
    assert sorted(table["method"]) == ["e3cm-plus", "sift", "xfeat"] and table["failed"].isna().all(), table
    assert list(table["rank"]) == [1, 2, 3] and (table["score_lo"] <= table["score_hi"]).all()
    assert (table["registered_images"] >= 15).all() and (table["seconds_per_image"] > 0).all()
    assert (out / "index.html").is_file()


@pytest.mark.slow  # three commands, each with its start-up: about 40 s on 2 cores
def test_an_edited_editable_plugin_is_refused_or_rematched_never_scored_stale(shared_data, tmp_path):
    """docs/own-matcher.md's plugin route as a researcher takes it: the example plugin installed
    editable (its source folder on the path and a dist-info naming its entry point, what `pip
    install -e` leaves), a run, an edit of its code that keeps its version, the same command
    again (refused in one line), then --overwrite (matched anew, the new settings recorded)."""
    entry = entry_point()
    if entry is None:
        pytest.skip("the e3cm-bench command is not installed (pip install -e .)")
    source, site = tmp_path / "src", tmp_path / "site"
    shutil.copytree(REPO / "examples/plugin/src/e3cm_bench_orb", source / "e3cm_bench_orb")
    info = site / "e3cm_bench_orb-0.1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: e3cm-bench-orb\nVersion: 0.1.0\n")
    (info / "entry_points.txt").write_text("[e3cm_bench.matchers]\norb = e3cm_bench_orb:ENTRY\n")
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "E3CM_BENCH_DEBUG")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(site), str(source), str(REPO), env.get("PYTHONPATH")]))
    command = [entry, "hpatches", "--root", str(shared_data / ROOTS["hpatches"]), *SMALL["hpatches"],
               "--out", str(tmp_path / "runs" / "orb"), "--matcher", "orb"]
    run = lambda *extra: subprocess.run(command + list(extra), env=env, capture_output=True, text=True,  # noqa: E731
                                        timeout=600)
    import yaml

    config = lambda: yaml.safe_load((tmp_path / "runs" / "orb" / "config.yaml").read_text())  # noqa: E731
    first = run()
    assert first.returncode == 0, first.stderr
    assert config()["matcher"]["max_keypoints"] == 5000
    old = config()["identity"]["plugin"]["sha256"]
    code = source / "e3cm_bench_orb" / "__init__.py"
    code.write_text(code.read_text().replace("max_keypoints: int = 5000", "max_keypoints: int = 1000"))
    again = run()
    assert again.returncode == 2 and "made with other settings" in again.stderr, again.stdout + again.stderr
    assert "evaluating only" not in again.stdout and config()["matcher"]["max_keypoints"] == 5000
    fresh = run("--overwrite")
    assert fresh.returncode == 0 and "evaluating only" not in fresh.stdout, fresh.stderr
    assert config()["matcher"]["max_keypoints"] == 1000
    # the refusal named the changed code with both values: the folder's hash and the edited code's
    new = config()["identity"]["plugin"]["sha256"]
    assert f"plugin code: sha256 {old[:12]}... -> {new[:12]}..." in again.stderr, again.stderr
    assert config()["identity"]["plugin"]["version"] == "0.1.0"  # the version never changed: the code did


def walk_env(*paths: Path) -> dict:
    """The environment of the walk's commands: no COLUMNS, no debug, `paths` then the repo first."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "E3CM_BENCH_DEBUG")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [*map(str, paths), str(REPO), env.get("PYTHONPATH")]))
    return env


def one_line(done: subprocess.CompletedProcess) -> str:
    """A refusal as the house rule has it: exit 2, one line on stderr, no traceback."""
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), done.stdout + done.stderr
    return lines[0]


# One start-up each (under a second idle): not slow.
def test_a_mistyped_matcher_suggests_sift(shared_data, tmp_path):
    entry = entry_point()
    if entry is None:
        pytest.skip("the e3cm-bench command is not installed (pip install -e .)")
    out = tmp_path / "runs" / "sift"
    done = subprocess.run([entry, "hpatches", "--root", str(shared_data / ROOTS["hpatches"]), *SMALL["hpatches"],
                           "--out", str(out), "--matcher", "sfit"], env=walk_env(), capture_output=True, text=True,
                          timeout=300)
    line = one_line(done)
    assert "unknown matcher 'sfit' (did you mean 'sift'?)" in line, line
    assert not out.exists()  # refused before the run folder is made


# A torch that says it was imported: on the path of the busy-folder command only.
TORCH_TRIPWIRE = "import os\nopen(os.environ['TORCH_TRIPWIRE'], 'w').close()\nraise ImportError('torch was imported')\n"


def test_a_busy_folder_is_refused_before_the_method_loads(shared_data, tmp_path):
    """The tour's deep matcher into a folder another run holds: refused in one line, with torch
    never imported (the tripwire torch first on the path would leave its file), and none of the
    lines a run prints once its method is built (the protocol line)."""
    entry = entry_point()
    if entry is None:
        pytest.skip("the e3cm-bench command is not installed (pip install -e .)")
    from e3cm_bench.storage.folder import RunFolder

    (tmp_path / "tripwire" / "torch").mkdir(parents=True)
    (tmp_path / "tripwire" / "torch" / "__init__.py").write_text(TORCH_TRIPWIRE)
    env = {**walk_env(tmp_path / "tripwire"), "TORCH_TRIPWIRE": str(tmp_path / "torch-imported")}
    out = tmp_path / "runs" / "e3cm"
    out.mkdir(parents=True)
    with RunFolder(out).lock():
        done = subprocess.run([entry, "hpatches", "--root", str(shared_data / ROOTS["hpatches"]), *SMALL["hpatches"],
                               "--out", str(out), "--matcher", "e3cm", "--backbone", "efficientnet_lite0"],
                              env=env, capture_output=True, text=True, timeout=300)
    line = one_line(done)
    assert f"{out}: another run is using this folder (pid {os.getpid()}" in line, line
    assert not (tmp_path / "torch-imported").exists(), line
    assert "protocol" not in done.stdout and not done.stdout.strip(), done.stdout


def broken_rows(text: str) -> list[str]:
    """The lines of a Markdown table row wrapped over several lines."""
    return [line for line in text.splitlines()
            if " | " in line and not (line.strip().startswith("|") and line.strip().endswith("|"))]


@pytest.mark.slow  # the walk runs every step once: about a minute
def test_compare_table_and_check_cut_no_cell_and_break_no_row(walk):
    # Fitting 80 columns by cutting words ("h_acc…", "no differe…") or by wrapping a Markdown
    # row over several lines is no better than overflowing: the reader loses the same text.
    narrow = [s for s in walk if s.words[0] in NARROW]
    cut = [f"{s.words[0]}: {line!r}" for s in narrow for line in s.stdout.splitlines() if "\u2026" in line]
    broken = [f"{s.words[0]}: {line!r}" for s in narrow for line in broken_rows(s.stdout)]
    assert not cut and not broken, "\n".join(cut[:10] + broken[:10])


def test_the_walk_finds_what_it_checks():
    # The width check would pass on empty output; the line reader would pass on no commands.
    assert commands("e3cm-bench a b  # note\ne3cm-bench c [--x 1] \\\n  --y 2\nls") == [["a", "b"], ["c", "--y", "2"]]
    assert bounded(["match", "a.jpg", "b.jpg"])[1] == str(SHARED / IMAGES["a.jpg"])
    assert bounded(["hpatches", "--out", "r", "--limit", "5"]).count("--limit") == 1
    assert broken_rows("| method | h_acc@1 |  \nh_acc@5 | n_pairs |\n| a | b |") == ["h_acc@5 | n_pairs |"]
