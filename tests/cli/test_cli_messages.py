"""The command line at once and in plain words: a mistyped name or a busy folder refused before
torch loads, 'did you mean', a refused rerun naming each setting with both values, a --root one
level too high naming the folder it should be, the protocol line of the benchmark run only,
counts as integers, listings within 80 columns."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from e3cm_bench.method.protocols import get_protocol
from e3cm_bench.ground.locks import FolderLock
from e3cm_bench.matchers import registry
from e3cm_bench.matchers.names import BUILTIN_MATCHERS
from e3cm_bench.drawing.formats import format_number
from e3cm_bench.storage.folder import RunFolder
from helpers import flat, invoke, one_line_error

REPO = Path(__file__).resolve().parents[2]

# The command line run in a fresh interpreter, which then says whether torch was imported.
PROBE = """
import sys
from e3cm_bench.cli import app
try:
    app(sys.argv[1:], prog_name="e3cm-bench")
except SystemExit as done:
    print(f"exit={done.code} torch={'torch' in sys.modules}")
"""


def probe(*args) -> tuple[str, str]:
    done = subprocess.run([sys.executable, "-c", PROBE, *map(str, args)], capture_output=True, text=True, timeout=300,
                          cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "COLUMNS": "300"})
    return done.stdout.strip().splitlines()[-1], done.stderr


def test_a_mistyped_matcher_is_refused_before_torch_loads(tmp_path):
    last, stderr = probe("hpatches", "--out", tmp_path / "run", "--matcher", "sfit")
    assert last == "exit=2 torch=False", (last, stderr)
    assert "unknown matcher 'sfit' (did you mean 'sift'?)" in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "run").exists()


def test_a_busy_folder_is_refused_before_torch_loads(tmp_path, shared_data):
    out = tmp_path / "run"
    with FolderLock(out):
        last, stderr = probe("hpatches", "--out", out, "--root", shared_data / "hpatches-sequences-release",
                             "--matcher", "e3cm", "--backbone", "efficientnet_lite0")
    assert last == "exit=2 torch=False", (last, stderr)
    assert "another run is using this folder" in stderr and "pid " in stderr


def test_check_free_takes_nothing(tmp_path):
    RunFolder(tmp_path).check_free()  # no lock file
    with FolderLock(tmp_path):
        with pytest.raises(ValueError, match="another run is using this folder"):
            RunFolder(tmp_path).check_free()
    RunFolder(tmp_path).check_free()
    with FolderLock(tmp_path):  # the probe left no lock behind
        pass


def test_did_you_mean_for_names(tmp_path):
    line = one_line_error(invoke("hpatches", "--out", tmp_path / "r", "--matcher", "sfit"))
    assert "did you mean 'sift'?" in line
    line = one_line_error(invoke("hpatches", "--out", tmp_path / "r", "--matcher", "e3cm", "--backbone", "vgg91"))
    assert "--backbone vgg91" in line and "did you mean 'vgg19'?" in line
    line = one_line_error(invoke("hpatches", "--out", tmp_path / "r", "--protocol", "defualt"))
    assert "did you mean 'default'?" in line
    line = one_line_error(invoke("import", "hpatchs", "--out", tmp_path / "r", "--npz", tmp_path))
    assert "unknown benchmark 'hpatchs' (did you mean 'hpatches'?)" in line
    result = invoke("hpatchs", "--out", tmp_path / "r")
    assert result.exit_code == 2 and "Did you mean 'hpatches'" in result.output
    # nothing close: no suggestion, the list as before
    line = one_line_error(invoke("hpatches", "--out", tmp_path / "r", "--matcher", "zzzz"))
    assert "did you mean" not in line and "choose one of: e3cm" in line


def test_the_builtin_names_are_the_registrys():
    registry._load()
    assert tuple(name for name, e in registry._REGISTRY.items() if e.origin == "built-in") == BUILTIN_MATCHERS


def test_a_refused_rerun_names_each_setting_with_both_values(tmp_path, shared_data):
    hp = shared_data / "hpatches-sequences-release"
    common = ["--root", hp, "--out", tmp_path / "run", "--matcher", "sift", "--limit", 1, "--sequences", "v_boat"]
    assert invoke("hpatches", *common, "--max-side", 160).exit_code == 0
    line = one_line_error(invoke("hpatches", *common, "--max-side", 120))
    assert "made with other settings (max_side 160 -> 120)" in line
    line = one_line_error(invoke("hpatches", *common, "--max-side", 120, "--set", "max_keypoints=500"))
    assert "max_side 160 -> 120" in line and "settings.max_keypoints 8000 (default) -> 500" in line


@pytest.mark.parametrize("benchmark, folder", [("hpatches", "hpatches-sequences-release"), ("evd", "EVD")])
def test_a_root_one_level_too_high_names_the_folder(benchmark, folder, tmp_path, shared_data):
    if not (shared_data / folder).is_dir():
        pytest.skip(f"{folder} not in the shared data")
    line = one_line_error(invoke(benchmark, "--root", shared_data, "--out", tmp_path / "r", "--matcher", "sift"))
    assert f"{shared_data} holds {folder}/: did you mean --root {shared_data / folder}?" in line


def test_the_protocol_line_says_what_applies_to_the_run():
    hpatches = get_protocol("default", "hpatches").line("hpatches")
    assert hpatches.startswith("protocol default on hpatches:") and "full size" in hpatches
    assert "YFCC" not in hpatches and "MegaDepth" not in hpatches and "1200" not in hpatches
    yfcc = get_protocol("default", "yfcc").line("yfcc")
    assert "upright" in yfcc and "1200" in yfcc
    evd = get_protocol("wxbs", "evd").line("evd")
    assert "H at 0.5 px" in evd and "F at 0.25" not in evd


def test_counts_print_as_integers():
    assert format_number(20.0, "registered_images") == "20"
    assert format_number(1577.0, "points") == "1577"
    assert format_number(3.0, "n_models") == "3" and format_number(15.0, "n_pairs") == "15"
    assert format_number(1577.4, "n_matches") == "1577.40"  # a mean over pairs keeps its decimals
    assert format_number(1.0, "mma@3") == "1.00"


def test_listings_fit_80_columns(shared_data):
    for args in (("matchers",), ("datasets", "--to", shared_data)):
        result = invoke(*args)
        assert result.exit_code == 0
        assert max(len(line) for line in result.output.splitlines()) <= 80, result.output
    assert "hpatches: incomplete at" in invoke("datasets", "--to", shared_data).output
    assert "cascade=true, estimator=top8" in flat(invoke("matchers").output)


def stderr_of(args, terminal_columns: int | None) -> str:
    """The command's stderr as it reaches a terminal `terminal_columns` wide (a pseudo-terminal
    on stdin and stderr, colours stripped), or a pipe (None); COLUMNS unset either way."""
    import os
    import re

    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES", "E3CM_BENCH_DEBUG")}
    env.update(PYTHONPATH=str(REPO), TERM="xterm")
    command = [sys.executable, "-m", "e3cm_bench", *map(str, args)]
    if terminal_columns is None:
        done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
        assert done.returncode == 2, done.stderr
        return done.stderr
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, terminal_columns, 0, 0))
    done = subprocess.run(command, stdin=slave, stdout=subprocess.DEVNULL, stderr=slave, env=env, timeout=300)
    os.close(slave)
    said = b""
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:  # EIO: the child's end is closed and all of it was read
            break
        if not chunk:
            break
        said += chunk
    os.close(master)
    assert done.returncode == 2, said
    return re.sub(r"\x1b\[[0-9;]*m", "", said.decode()).replace("\r\n", "\n")


def test_an_error_wraps_on_a_terminal_and_stays_one_line_elsewhere(tmp_path):
    # A terminal gets the error within its width, continuation lines under the text after
    # "error: "; a pipe (grep, CI, a log, a script reading stderr's last line) gets one physical
    # line, all of it: the one-line rule is about what a program reads (docs/cli.md, "Output").
    args = ("hpatches", "--out", tmp_path / "run", "--matcher", "sfit")
    piped = stderr_of(args, None)
    assert piped.count("\n") == 1 and len(piped) > 120, piped
    assert piped.startswith("error: unknown matcher 'sfit' (did you mean 'sift'?); choose one of: e3cm")
    shown = stderr_of(args, 60).splitlines()
    assert len(shown) > 2 and max(map(len, shown)) <= 60, shown
    assert shown[0].startswith("error: unknown matcher 'sfit'")
    assert all(line.startswith(" " * 7) and line[7] != " " for line in shown[1:]), shown
    assert " ".join(line.strip() for line in shown) == piped.strip()  # the same words, none cut


def test_export_fits_80_columns_in_a_pipe_from_a_wide_terminal(tmp_path, shared_data):
    # `e3cm-bench export ... > log` typed at a 200-column terminal: stdout is a file, so its
    # lines are laid out for 80 columns (rich alone would take stdin's terminal's width).
    import os
    import pty

    run = tmp_path / "sift"
    assert invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--sequences", "v_boat",
                  "--limit", 1, "--max-side", 160, "--out", run, "--matcher", "sift").exit_code == 0
    import fcntl
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 200, 0, 0))
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    out = tmp_path / "a-long-folder-name" / "exported"
    done = subprocess.run([sys.executable, "-m", "e3cm_bench", "export", str(run), str(out), "--to", "colmap"],
                          stdin=slave, capture_output=True, text=True, timeout=300, env={**env, "PYTHONPATH": str(REPO)})
    os.close(slave)
    os.close(master)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    # a path longer than a line is kept whole on a line of its own, never cut
    assert lines and all(len(line) <= 80 or " " not in line.strip() for line in lines), done.stdout
    assert max(map(len, lines)) < 120 and f"of {run} -> colmap in {out} (pixel origin" in flat(done.stdout)
