"""Small helpers shared by several test files (imported as `helpers`; pytest puts tests/ on the path)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import h5py
import numpy as np


def rotation(axis: str, degrees: float) -> np.ndarray:
    """3x3 rotation about one coordinate axis."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def one_line_error(result) -> str:
    """A clean CLI failure: exit code 2, exactly one line on stderr, no traceback."""
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    assert "Traceback" not in result.output
    return lines[0]


def flat(text: str) -> str:
    """Output with rich's line wrapping undone (whitespace runs -> one space)."""
    return " ".join(text.split())


def gluefactory_layout(scene_infos, folder, image_for) -> int:
    """Writes the pairs of LoFTR scene_info files into glue-factory's megadepth1500 layout under
    `folder` (views.txt, pairs.txt, images/ named by basename), in the lists' order; written
    here from the layout's description, independently of the reader. image_for(path relative
    to the LoFTR root, destination) places each image. Returns the number of pairs."""
    from pathlib import Path

    from e3cm_bench.datasets.megadepth import load_scene_info

    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    views, pairs = {}, []
    for path in scene_infos:
        scene = load_scene_info(Path(path))
        for (i, j), *_ in scene["pair_infos"]:
            names = []
            for k in (i, j):
                relative = str(scene["image_paths"][k])
                name = Path(relative).name
                if name not in views:
                    K, P = np.asarray(scene["intrinsics"][k], float), np.asarray(scene["poses"][k], float)
                    numbers = [*P[:3, :3].ravel(), *P[:3, 3]]
                    views[name] = " ".join([name, *(repr(float(v)) for v in numbers), "PINHOLE", "8", "8",
                                            *(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))])
                    image_for(relative, folder / "images" / name)
                names.append(name)
            pairs.append(" ".join(names))
    (folder / "views.txt").write_text("\n".join(views.values()) + "\n")
    (folder / "pairs.txt").write_text("\n".join(pairs) + "\n")
    return len(pairs)


def cached_arrays(folder: Path) -> dict:
    out = {}
    with h5py.File(folder / "matches.h5") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_arrays(folder: Path, reference: Path) -> None:
    got, want = cached_arrays(folder), cached_arrays(reference)
    assert got.keys() == want.keys() and len(want) > 0
    for name in want:
        assert np.array_equal(got[name], want[name]), name


def invoke(*args, **kwargs):
    """Run the CLI in-process (kwargs: CliRunner.invoke's, e.g. input); print the command and
    everything it said (pytest shows it on failure)."""
    from typer.testing import CliRunner

    from e3cm_bench.cli import app

    result = CliRunner().invoke(app, [str(a) for a in args], **kwargs)
    print(f"$ e3cm-bench {' '.join(str(a) for a in args)}\n{result.output}")
    return result


def replay_stage(cache, files_in_order: list[tuple[str, str]], maps, plan: bool = True) -> None:
    """Drive a FeatureCache as the match stage does (pipeline/stage.py): told the order (plan; else
    it evicts the least recently used), then per pair `at`, get or put each image's maps
    (maps(file)), and done_with after an image's last pair."""
    last = {f: k for k, files in enumerate(files_in_order) for f in files}
    if plan:
        cache.plan(files_in_order)
    for k, files in enumerate(files_in_order):
        cache.at(k, files)
        for which, f in enumerate(files):
            cache.belongs_to(f, which)
            if cache.get(f) is None:
                cache.put(f, maps(f))
        for f in dict.fromkeys(files):
            if last[f] == k:
                cache.done_with(f)


def accuracy_summary(path: Path):
    """A run's summary.csv without its cost columns (seconds_per_pair and its interval, peak
    memory: measurements that move between two runs of the same matches), as a DataFrame."""
    import pandas as pd

    from e3cm_bench.pipeline.evaluate import COST_KEYS

    summary = pd.read_csv(path)
    cost = [c for c in summary.columns if c in COST_KEYS or c.removesuffix("_lo").removesuffix("_hi") in COST_KEYS]
    return summary.drop(columns=cost)


def same_csvs(a: Path, b: Path) -> None:
    """Two run folders hold the same per-pair rows byte for byte and the same summary numbers
    (their cost columns aside: each run measured its own time and memory)."""
    import pandas as pd

    assert (a / "per_pair.csv").read_bytes() == (b / "per_pair.csv").read_bytes(), "per_pair.csv"
    pd.testing.assert_frame_equal(accuracy_summary(a / "summary.csv"), accuracy_summary(b / "summary.csv"),
                                  check_exact=True, obj="summary.csv")


def same_tables(a: Path, b: Path) -> None:
    """Two `table` CSVs with the same rows and numbers, their runs' cost columns aside."""
    import pandas as pd

    from e3cm_bench.pipeline.evaluate import COST_KEYS
    from e3cm_bench.reporting.notes import COST_NOTE

    def accuracy(path: Path):  # the cost note names the load the run met: a measurement too
        table = pd.read_csv(path)
        return table.drop(columns=[c for c in table.columns
                                   if c == COST_NOTE or c.removesuffix("_lo").removesuffix("_hi") in COST_KEYS])

    pd.testing.assert_frame_equal(accuracy(a), accuracy(b), check_exact=True, obj=str(a))


def kitti_frames(shared_data: Path, n: int, path: Path) -> Path:
    """A scene_info at `path` holding the first `n` of the shared KITTI 00 frames (the other
    images' paths left out, None), so that an sfm set stays small."""
    from e3cm_bench.datasets.megadepth import load_scene_info

    scene = load_scene_info(shared_data / "megadepth_test_1500" / "scene_info" / "kitti00_seq.npz")
    paths = np.array(scene["image_paths"], dtype=object)
    paths[n:] = None
    np.savez(path, image_paths=paths, intrinsics=scene["intrinsics"], poses=scene["poses"],
             pair_infos=scene["pair_infos"])
    return path


def sift_hpatches_run(shared_data: Path, out: Path, max_side: int = 240, limit: int = 2) -> Path:
    """A small SIFT run on the shared HPatches sample in `out` (the reporting tests' run)."""
    result = invoke("hpatches", "--root", shared_data / "hpatches-sequences-release", "--out", out, "--matcher", "sift",
                    "--max-side", max_side, "--limit", limit)
    assert result.exit_code == 0, result.output
    return out


def table_lines(text: str) -> list[str]:
    """The lines of a command's output that belong to a table or listing (columns two spaces or
    more apart, or a rule): in a pipe these are laid out for 80 columns, while a message is one
    line however long (docs/cli.md, Output)."""
    return [line for line in text.splitlines() if re.search(r"\S {2,}\S|[─━│┃]", line.strip())]
