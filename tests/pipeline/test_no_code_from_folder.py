"""No code from the current folder: a ``--matcher module:factory`` takes that one module from the
folder, and nothing else (a dataset folder holding a PIL.py, a json.py, a torch.py), in this
process, in --workers processes and in --launcher slurm's tasks (issue 61, item 1).

The command runs as the installed ``e3cm-bench`` script does (a launcher file whose own folder,
not the current one, is first on the path), in a fresh process whose current folder holds the
decoys; each decoy writes a marker file and raises when imported."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
# names a matcher run imports (PIL, torch, cv2, h5py, yaml, json), and what a spawned worker
# imports before it is given its parent's path (pickle, socket)
DECOYS = ("PIL", "json", "torch", "yaml", "h5py", "cv2", "pickle", "socket", "numpy")
LAUNCHER = """import sys
from e3cm_bench.__main__ import main
if __name__ == '__main__':
    sys.exit(main())
"""
MINE = """import numpy as np
from e3cm_bench import Matcher, Matches

class Mine(Matcher):
    name = "mine"
    keypoints_in_image = True
    def match(self, image0, image1):
        k = np.array([[10.0, 10.0], [20.0, 30.0], [40.0, 15.0], [25.0, 25.0], [30.0, 40.0]])
        return Matches(k, k + 1, np.ones(len(k)))

def build():
    return Mine()
"""


@pytest.fixture(scope="module")
def boat(shared_data, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "hpatches"
    shutil.copytree(shared_data / "hpatches-sequences-release" / "v_boat", root / "v_boat")
    return root


@pytest.fixture
def decoyed(tmp_path) -> Path:
    """A current folder holding the decoys; their markers go to tmp_path/markers."""
    here, markers = tmp_path / "here", tmp_path / "markers"
    here.mkdir()
    markers.mkdir()
    for name in DECOYS:
        (here / f"{name}.py").write_text(f"open({str(markers / name)!r}, 'w').write('ran')\n"
                                         f"raise ImportError('decoy {name} imported')\n")
    return here


def e3cm_bench(args: list, cwd: Path, pythonpath: list[Path] = (), without_srun: bool = False) -> subprocess.CompletedProcess:
    """The command as the installed script runs it (its own folder first on the path, not the current one)."""
    script = cwd.parent / "bin" / "e3cm-bench"
    script.parent.mkdir(exist_ok=True)
    script.write_text(LAUNCHER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, [ROOT, *pythonpath]))}
    env.pop("PYTHONSAFEPATH", None)
    if without_srun:  # submitit then runs the array's tasks here, as local processes
        env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if not (Path(p) / "srun").exists())
    return subprocess.run([sys.executable, str(script), *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def assert_no_decoy_ran(done: subprocess.CompletedProcess, decoyed: Path) -> None:
    ran = sorted(p.name for p in (decoyed.parent / "markers").iterdir())
    assert ran == [], f"decoys imported from the current folder: {ran}\n{done.stderr[-2000:]}"
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]


# workers=2: 9 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
@pytest.mark.parametrize("workers", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_a_module_factory_in_the_current_folder_brings_nothing_else_from_it(boat, decoyed, workers):
    (decoyed / "mine.py").write_text(MINE)
    out = decoyed.parent / "out"
    done = e3cm_bench(["hpatches", "--root", boat, "--out", out, "--matcher", "mine:build", "--limit", 4,
                       "--workers", workers], decoyed)
    assert_no_decoy_ran(done, decoyed)
    per_pair = pd.read_csv(out / "per_pair.csv")
    assert len(per_pair) == 4 and (per_pair["n_matches"] == 5).all()


def test_a_package_in_the_current_folder_is_found_with_its_submodules_in_workers(boat, decoyed):
    package = decoyed / "mine_pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "fixed.py").write_text(MINE)
    out = decoyed.parent / "out"
    done = e3cm_bench(["hpatches", "--root", boat, "--out", out, "--matcher", "mine_pkg.fixed:build", "--limit", 4,
                       "--workers", 2], decoyed)
    assert_no_decoy_ran(done, decoyed)
    assert len(pd.read_csv(out / "per_pair.csv")) == 4


def test_a_module_factory_on_the_python_path_adds_no_folder(boat, decoyed):
    elsewhere = decoyed.parent / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mine_on_path.py").write_text(MINE)
    out = decoyed.parent / "out"
    done = e3cm_bench(["hpatches", "--root", boat, "--out", out, "--matcher", "mine_on_path:build", "--limit", 2],
                      decoyed, pythonpath=[elsewhere])
    assert_no_decoy_ran(done, decoyed)


@pytest.mark.slow  # 15 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_slurm_tasks_import_nothing_from_the_current_folder(boat, decoyed, monkeypatch):
    """--launcher slurm where no SLURM is found: submitit's local tasks (``python -m``)."""
    pytest.importorskip("submitit")
    (decoyed / "mine.py").write_text(MINE)
    out = decoyed.parent / "out"
    done = e3cm_bench(["hpatches", "--root", boat, "--out", out, "--matcher", "mine:build", "--limit", 2,
                       "--launcher", "slurm", "--shards", 2], decoyed, without_srun=True)
    assert_no_decoy_ran(done, decoyed)
    assert len(pd.read_csv(out / "per_pair.csv")) == 2
