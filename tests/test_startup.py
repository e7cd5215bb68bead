"""The command line answers before it loads the heavy libraries: importing e3cm_bench.cli
(what every invocation does before typer reads its arguments, `--help` and a typo included)
loads neither torch nor scipy, and the help texts read as written. The time it takes is
measured by scripts/maintain/startup_time.py, not here."""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest
import typer
from rich.text import Text

from e3cm_bench import __version__


def loaded_by(code: str) -> list[str]:
    """The heavy libraries in sys.modules after `code`, in a fresh interpreter."""
    probe = (f"import sys\n{code}\n"
             "import json; print(json.dumps([m for m in ('torch', 'torchvision', 'scipy', 'matplotlib', 'h5py') "
             "if m in sys.modules]))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_importing_the_command_line_loads_neither_torch_nor_scipy():
    assert loaded_by("import e3cm_bench.cli") == []


@pytest.mark.parametrize("args", [["--help"], ["hpatches", "--help"], ["hpatchez"], ["--version"]])
def test_help_a_typo_and_the_version_load_neither_torch_nor_scipy(args):
    # The whole command, typer's parsing and help included, not only the import.
    code = ("import sys; sys.argv = ['e3cm-bench', *%r]\nfrom e3cm_bench.__main__ import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass" % (args,))
    assert loaded_by(code) == []


def test_the_probe_sees_torch_when_it_is_loaded():
    # The check above could pass by looking at the wrong interpreter; here it must find torch.
    assert "torch" in loaded_by("import e3cm_bench.backbones.loading")


def test_version(tmp_path):
    from typer.testing import CliRunner

    from e3cm_bench.cli import app

    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"e3cm-bench {__version__}"


def test_the_backbone_names_are_those_the_backbones_build():
    from e3cm_bench.backbones import names as backbone_names, loading as backbones

    assert tuple(backbones.SPECS) == backbone_names.BACKBONES
    assert backbone_names.DEFAULT_BACKBONE in backbones.SPECS and backbone_names.OFFLINE_BACKBONE in backbones.SPECS


def _help_texts(command: click.Command, path: str = "e3cm-bench"):
    """(where, text) of every help text the app shows: commands' and their options'."""
    if command.help:
        yield path, command.help
    for param in command.params:
        if getattr(param, "help", None):
            yield f"{path} {param.opts[0] if param.opts else param.name}", param.help
    for name, sub in getattr(command, "commands", {}).items():  # typer's group is no click.Group
        yield from _help_texts(sub, f"{path} {name}")


def test_every_help_text_reads_as_written_under_rich_markup():
    # typer prints help texts as Rich markup, where "[word]" is a style and disappears (it ate
    # "[poselib]" of "pip install 'e3cm-bench[poselib]'"): a literal bracket needs "\[".
    from e3cm_bench.cli import app

    texts = list(_help_texts(typer.main.get_command(app)))
    assert len(texts) > 100
    lost = [(where, text) for where, text in texts if Text.from_markup(text).plain != text.replace("\\[", "[")]
    assert not lost, lost
    pose = next(text for where, text in texts if where.endswith("hpatches --pose-estimator"))
    assert "pip install 'e3cm-bench[poselib]'" in Text.from_markup(pose).plain
