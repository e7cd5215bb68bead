"""Bounded before allocating, and one line instead of a traceback (issue 61, items 5 and 6): a
scene_info whose lists expand to gigabytes, an sfm graph of millions of pairs, shard counts and
indices, --launcher slurm without a controller, `import sfm`, a short scene_info, a full disk
while the sfm database is written, OUT/sfm a file, a broken library, and Rich markup in paths."""

from __future__ import annotations

import os
import pickle
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from e3cm_bench.datasets.megadepth import load_scene_info
from e3cm_bench.pipeline import launch
from helpers import flat, invoke, one_line_error

ROOT = Path(__file__).resolve().parents[2]
SCENE_INFO = "megadepth_test_1500/scene_info/kitti00_seq.npz"
HPATCHES = "hpatches-sequences-release"


def command(*args, cwd: Path | None = None, env: dict | None = None, limit_kb: int | None = None):
    """`python -m e3cm_bench ARGS` in a fresh process (an address-space limit where given)."""
    def limit():
        if limit_kb is not None:
            resource.setrlimit(resource.RLIMIT_AS, (limit_kb * 1024, resource.RLIM_INFINITY))

    environment = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-m", "e3cm_bench", *map(str, args)], cwd=cwd, env=environment,
                          capture_output=True, text=True, timeout=600, preexec_fn=limit)


def one_line(done: subprocess.CompletedProcess) -> str:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), done.stderr[-3000:]
    return lines[0]


# --------------------------------------------------------------------------- 5. bounded


@pytest.fixture(scope="module")
def limit_kb(tmp_path_factory) -> int:
    """The address space of a process that has imported what the commands import, plus 2 GiB:
    the bounded commands stay far below it; what main did (6 GB and more) meets it."""
    if not Path("/proc/self/status").is_file():
        pytest.skip("reads VmSize from /proc (Linux)")
    probe = "import re, e3cm_bench.cli, e3cm_bench.pipeline.runner, cv2, h5py, torch\n" \
            "print(re.search(r'VmSize:\\s+(\\d+)', open('/proc/self/status').read()).group(1))"
    done = subprocess.run([sys.executable, "-c", probe], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          cwd=tmp_path_factory.mktemp("probe"), capture_output=True, text=True, check=True, timeout=300)
    return int(done.stdout) + (2 << 20)


def expanding_scene(kind: str) -> dict:
    """A scene_info of a few hundred bytes whose lists expand to about a billion values."""
    if kind == "deep":  # a list holding one list twice, 30 levels deep: 2**30
        x = [0.0, 0.0]
        for _ in range(30):
            x = [x, x]
    else:  # three levels of a list holding one list 1000 times: 1000**3
        x = [0.0] * 1000
        for _ in range(2):
            x = [x] * 1000
    return {"image_paths": np.array(["a.png", "b.png"], dtype=object), "intrinsics": x, "poses": x,
            "pair_infos": [((0, 1), 0.5, np.zeros(3))], "depth_paths": []}


@pytest.mark.parametrize("kind", ["deep", "wide"])
def test_a_small_scene_info_that_expands_to_gigabytes_is_refused_before_it_is_used(tmp_path, kind, limit_kb):
    scene_info = tmp_path / "scene_info" / "hostile.npz"
    scene_info.parent.mkdir()
    scene_info.write_bytes(pickle.dumps(expanding_scene(kind)))
    assert scene_info.stat().st_size < 20_000
    for args in (["sfm", "--root", tmp_path, "--scene-info", scene_info], ["megadepth", "--root", tmp_path]):
        # main filled 6 GB here
        line = one_line(command(*args, "--matcher", "sift", "--out", tmp_path / "out", limit_kb=limit_kb))
        assert f"{scene_info}: not a scene_info file (" in line
        assert ("nested deeper" if kind == "deep" else "expands to over") in line


def test_the_real_scene_infos_are_within_the_bounds(shared_data):
    for path in sorted((shared_data / "megadepth_test_1500" / "scene_info").glob("*.npz")):
        assert len(load_scene_info(path)["image_paths"]) > 0


def big_set(shared_data: Path, folder: Path, n: int) -> tuple[Path, Path]:
    """A scene_info of n images: the first 3 are KITTI frames (linked under folder), the others
    named but absent; K and poses are KITTI's, repeated."""
    scene = load_scene_info(shared_data / SCENE_INFO)
    root = folder / "root"
    (root / "images").mkdir(parents=True)
    for i in range(3):
        (root / "images" / f"{i:05d}.png").symlink_to(shared_data / "megadepth_test_1500" / scene["image_paths"][i])
    count = len(scene["image_paths"])
    scene_info = folder / "big.npz"
    np.savez(scene_info, image_paths=np.array([f"images/{i:05d}.png" for i in range(n)], dtype=object),
             intrinsics=np.array([scene["intrinsics"][i % count] for i in range(n)]),
             poses=np.array([scene["poses"][i % count] for i in range(n)]), pair_infos=scene["pair_infos"])
    return root, scene_info


def test_an_exhaustive_graph_is_counted_and_capped_before_it_is_built_and_limit_cuts_it(shared_data, tmp_path, limit_kb):
    root, scene_info = big_set(shared_data, tmp_path, 3000)
    args = ["sfm", "--root", root, "--scene-info", scene_info, "--matcher", "sift", "--max-side", 320]
    line = one_line(command(*args, "--out", tmp_path / "all", limit_kb=limit_kb))
    assert "3000 images give 4,498,500 pairs (every pair), over the 20,000 a run builds; --max-pairs 4498500" in line
    line = one_line(command(*args, "--window", 10, "--max-pairs", 100, "--out", tmp_path / "window"))
    assert "3000 images give 29,945 pairs (its graph), over the 100 a run builds" in line
    # --limit: only the pairs the run reaches are made (those of the three images present)
    done = command(*args, "--limit", 2, "--out", tmp_path / "limited", limit_kb=limit_kb)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "sfm: 2 pairs" in flat(done.stdout)


def test_shard_counts_and_indices_are_checked_before_anything_runs(shared_data, tmp_path):
    base = ["hpatches", "--root", shared_data / HPATCHES, "--matcher", "sift", "--limit", 10, "--max-side", 200]
    line = one_line_error(invoke(*base, "--out", tmp_path / "a", "--shard", "1/20"))
    assert line == "error: --shard 1/20: 20 shards of 10 pair(s) would leave some with none; choose N of at most 10"
    assert not (tmp_path / "a").exists()
    line = one_line_error(invoke(*base, "--out", tmp_path / "b", "--shard", "1/1000000000"))
    assert "at most 100,000 shards" in line
    line = one_line_error(invoke(*base, "--out", tmp_path / "c", "--shards", -3))
    assert "--shards -3 applies to --launcher slurm" in line
    line = one_line_error(invoke(*base, "--out", tmp_path / "d", "--shards", -3, "--launcher", "slurm"))
    assert "--shards must be from 1 to 100,000, got -3" in line


def test_slurm_shards_without_srun_obey_the_process_limit_of_workers(shared_data, tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep)
                                              if not (Path(p) / "srun").exists()))
    monkeypatch.setattr(launch, "max_cpu_workers", lambda: (2, "2 cores"))
    line = one_line_error(invoke("hpatches", "--root", shared_data / HPATCHES, "--out", tmp_path / "o", "--matcher",
                                 "sift", "--limit", 6, "--max-side", 100, "--launcher", "slurm", "--shards", 6))
    assert "--launcher slurm --shards 6 (no srun here: submitit starts them as local processes): this machine " \
           "holds at most 2 (2 cores)" in line
    assert not (tmp_path / "o").exists()


def test_srun_on_path_without_a_controller_is_one_line(shared_data, tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "sinfo").write_text("#!/bin/sh\necho 'sinfo: error: Unable to contact slurm controller' >&2\nexit 1\n")
    for tool in ("srun", "sinfo"):
        (bin_dir / tool).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    line = one_line_error(invoke("hpatches", "--root", shared_data / HPATCHES, "--out", tmp_path / "o", "--matcher",
                                 "sift", "--limit", 2, "--launcher", "slurm", "--shards", 2))
    assert "srun is on PATH but no SLURM controller answers (sinfo -h: sinfo: error: Unable to contact" in line


@pytest.mark.parametrize("shards, says", [("1000000000", "at most 100,000 shards"),
                                          ("1e9", "E3CM_SHARDS=1e9 is not a whole number of shards")])
def test_the_array_script_refuses_a_shard_count_it_cannot_hold(shared_data, tmp_path, shards, says):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "e3cm-bench").write_text(f"#!/bin/sh\nexec {sys.executable} -m e3cm_bench \"$@\"\n")
    (bin_dir / "e3cm-bench").chmod(0o755)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
           "E3CM_SHARDS": shards, "SLURM_ARRAY_TASK_ID": "1"}
    done = subprocess.run(["bash", str(ROOT / "scripts" / "slurm" / "array.sh"), "hpatches", "--root",
                           str(shared_data / HPATCHES), "--out", str(tmp_path / "o"), "--matcher", "sift", "--limit", "3"],
                          env=env, capture_output=True, text=True, timeout=300)
    lines = [line for line in done.stderr.splitlines() if line.strip() and "integer expression" not in line]
    assert done.returncode == 2 and len(lines) == 1 and says in lines[0], done.stderr[-3000:]


# --------------------------------------------------------------------------- 6. one line


@pytest.fixture(scope="module")
def sfm_run(shared_data, tmp_path_factory) -> tuple[list, Path]:
    """An sfm run over 6 KITTI frames (window 2): its command and its folder."""
    scene = load_scene_info(shared_data / SCENE_INFO)
    paths = np.array(scene["image_paths"], dtype=object)
    paths[6:] = None
    folder = tmp_path_factory.mktemp("sfm")
    scene_info = folder / "kitti6.npz"
    np.savez(scene_info, image_paths=paths, intrinsics=scene["intrinsics"], poses=scene["poses"],
             pair_infos=scene["pair_infos"])
    args = ["sfm", "--root", shared_data / "megadepth_test_1500", "--scene-info", scene_info, "--window", 2,
            "--matcher", "sift"]
    result = invoke(*args, "--out", folder / "run")
    assert result.exit_code == 0, result.output
    return args, folder / "run"


def copy_of_matches(run: Path, folder: Path) -> Path:
    folder.mkdir(exist_ok=True)
    for name in ("config.yaml", "matches.h5"):
        shutil.copy(run / name, folder / name)
    return folder


def test_out_sfm_a_regular_file_is_one_line_and_kept(sfm_run, tmp_path):
    args, run = sfm_run
    out = copy_of_matches(run, tmp_path / "run")
    (out / "sfm").write_text("mine")
    line = one_line_error(invoke(*args, "--out", out, "--eval-only"))
    assert line == f"error: {out / 'sfm'}: is not a folder (the reconstruction's files go there); move it away and rerun"
    assert (out / "sfm").read_text() == "mine"


def test_a_full_disk_while_the_sfm_database_is_written_is_one_line(sfm_run, tmp_path):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root")
    args, run = sfm_run
    small = tmp_path / "small"
    small.mkdir()
    size = sum((run / name).stat().st_size for name in ("config.yaml", "matches.h5")) // 1024 + 100
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}k", "tmpfs", str(small)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({mounted.stderr.decode().strip()})")
    try:
        out = copy_of_matches(run, small / "run")
        line = one_line_error(invoke(*args, "--out", out, "--eval-only"))
        assert line.startswith(f"error: {out / 'sfm' / 'database.db'}: no space left on device")
        assert sorted(p.name for p in (out / "sfm").iterdir()) == []  # no SQLite leftovers
        assert (out / "matches.h5").stat().st_size == (run / "matches.h5").stat().st_size
    finally:
        subprocess.run(["umount", "-l", str(small)], capture_output=True)


def test_import_sfm_takes_its_one_scene_info(sfm_run, tmp_path):
    args, _ = sfm_run
    scene_info = args[args.index("--scene-info") + 1]
    database = tmp_path / "not.db"
    database.write_text("not a database")
    line = one_line_error(invoke("import", "sfm", "--root", args[2], "--scene-info", scene_info, "--window", 2,
                                 "--colmap", database, "--out", tmp_path / "o"))
    assert line.startswith(f"error: {database}: ")  # the database read, the scene_info taken as one path
    line = one_line_error(invoke("import", "sfm", "--root", args[2], "--scene-info", scene_info, "--scene-info",
                                 scene_info, "--colmap", database, "--out", tmp_path / "o"))
    assert line == "error: --scene-info: sfm takes one, given 2"


@pytest.mark.parametrize("short", ["intrinsics", "poses"])
def test_a_scene_info_with_fewer_intrinsics_or_poses_than_images_is_one_line(shared_data, tmp_path, short):
    scene = load_scene_info(shared_data / SCENE_INFO)
    arrays = {key: scene[key] for key in ("image_paths", "intrinsics", "poses", "pair_infos")}
    arrays[short] = arrays[short][:5]
    bad = tmp_path / "short.npz"
    np.savez(bad, **arrays)
    for benchmark, extra in (("sfm", ["--scene-info", bad]), ("megadepth", ["--scene-info", bad])):
        line = one_line_error(invoke(benchmark, "--root", shared_data / "megadepth_test_1500", *extra,
                                     "--matcher", "sift", "--out", tmp_path / benchmark))
        assert line == f"error: {bad}: {short} has 5 entries for 20 images (image_paths); a scene_info has one per image"


@pytest.mark.parametrize("library, command_args", [
    ("cv2", ["--help"]), ("yaml", ["--help"]), ("yaml", ["hpatches", "--matcher", "sift"]),
    ("h5py", ["hpatches", "--matcher", "sift"]), ("torch", ["hpatches", "--matcher", "sift"]),
])
def test_a_broken_library_is_one_line_naming_it(shared_data, tmp_path, library, command_args):
    broken = tmp_path / "broken" / library
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text(f"raise ImportError('lib{library}.so: cannot open shared object file')\n")
    runs = ["--root", shared_data / HPATCHES, "--out", tmp_path / "o", "--limit", 1] if "sift" in command_args else []
    done = command(*command_args, *runs, cwd=tmp_path, env={"PYTHONPATH": f"{broken.parent}{os.pathsep}{ROOT}"})
    line = one_line(done)
    assert line.startswith(f"error: the library {library} could not be imported (ImportError: lib{library}.so: ")
    assert "pip install --force-reinstall" in line


def test_rich_markup_never_reads_user_paths_or_messages(shared_data, tmp_path, monkeypatch):
    root = tmp_path / "r[/]x"  # a folder "r[" holding "]x"
    root.mkdir(parents=True)
    line = one_line_error(invoke("hpatches", "--root", root, "--out", tmp_path / "o[/]y", "--matcher", "sift"))
    assert line.startswith(f"error: {root}")
    out = tmp_path / "o[red]z[/]"
    result = invoke("hpatches", "--root", shared_data / HPATCHES, "--out", out, "--matcher", "sift", "--limit", 1,
                    "--max-side", 100)
    assert result.exit_code == 0 and (out / "matches.h5").is_file()
    again = invoke("hpatches", "--root", shared_data / HPATCHES, "--out", out, "--matcher", "sift", "--limit", 1,
                   "--max-side", 100)
    unwrapped = "".join(again.output.split())  # rich wraps a long path anywhere
    assert f"all1pairsfoundin{out / 'matches.h5'}".replace(" ", "") in unwrapped
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # not installed
    line = one_line_error(invoke("sfm", "--root", tmp_path, "--colmap-model", tmp_path, "--matcher", "sift",
                                 "--out", tmp_path / "sfm"))
    assert "pip install 'e3cm-bench[colmap]'" in line
