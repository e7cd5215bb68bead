"""The public Python API: the documentation's example, the benchmark registry, MethodSpec identity."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

import e3cm_bench as eb
from e3cm_bench.benchmarks import BENCHMARKS, HomographyBenchmark
from e3cm_bench.datasets.base import Pair, PairList
from e3cm_bench.apps.synth.textures import demo_homography, procedural_scene
from e3cm_bench.pipeline.experiments import write_table

REPO_ROOT = Path(__file__).resolve().parents[1]


def readme_python_example() -> str:
    """The runnable ```python block of the documentation's Python API page."""
    text = (REPO_ROOT / "docs" / "api.md").read_text()
    return re.search(r"<!-- runnable -->\n```python\n(.*?)```", text, re.S).group(1)


@pytest.mark.slow  # 38 s in the fast set under a load of about 7 on the shared 2-core machine (docs/development.md, Testing)
def test_readme_example_runs_as_written(shared_data, tmp_path):
    code = readme_python_example()
    assert "eb.match_pair" in code and "eb.run_benchmark" in code
    # Run from a checkout-like folder: ../shared/data resolves to the real samples, and the
    # example's run folder lands in tmp_path.
    work = tmp_path / "checkout"
    work.mkdir()
    code = code.replace("../shared/data", str(shared_data)).replace("runs/api-example", str(tmp_path / "api-run"))
    done = subprocess.run([sys.executable, "-c", code], cwd=work, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    print(done.stdout[-1500:])
    first = done.stdout.splitlines()[0]
    n_matches = int(first.split()[0])
    assert n_matches > 200, first  # v_boat 1-2 at 640 px with Lite0
    summary = pd.read_csv(tmp_path / "api-run" / "summary.csv")
    assert summary["n_pairs"].item() == 2 and 0 < summary["mma@3"].item() <= 1


def test_match_pair_maps_to_original_pixels(shared_data):
    """match_pair on paths with a resize equals matching the resized arrays and mapping back."""
    matcher = eb.build_matcher("sift")
    seq = shared_data / "hpatches-sequences-release" / "v_boat"
    m = eb.match_pair(matcher, seq / "1.ppm", seq / "2.ppm", max_side=400)
    assert m.info["size0"] == (850, 680) and max(m.info["match_size0"]) == 400
    H = np.loadtxt(seq / "H_1_2")
    projected = cv2.perspectiveTransform(m.keypoints0[None].astype(np.float64), H)[0]
    errors = np.linalg.norm(projected - m.keypoints1, axis=1)
    assert np.median(errors) < 3.0  # in original pixels: the ground truth is in original pixels


# --------------------------------------------------------------------------- a toy benchmark


class ToyHomographies(PairList):
    """Pairs written by the test: a procedural scene and its warps by known homographies."""

    def __init__(self, root, skip_bad: bool = False, n_pairs: int = 2):
        root = Path(root)
        pairs = []
        for k in range(n_pairs):
            image = procedural_scene((320, 240), seed=k)
            H = demo_homography((320, 240))
            a, b = root / f"s{k}_a.png", root / f"s{k}_b.png"
            cv2.imwrite(str(a), image[..., ::-1])
            cv2.imwrite(str(b), cv2.warpPerspective(image, H, (320, 240), borderMode=cv2.BORDER_REFLECT)[..., ::-1])
            pairs.append(Pair(f"v_toy{k}/1-2", a, b, H=H, meta={"sequence": f"v_toy{k}"}))
        self.n_pairs = n_pairs
        super().__init__(pairs, source=root, skip_bad=skip_bad)

    def settings(self) -> dict:
        return {"n_pairs_made": self.n_pairs}


@pytest.fixture
def toy_benchmark():
    benchmark = eb.register(HomographyBenchmark(name="toy", dataset=ToyHomographies, dataset_options=("n_pairs",)))
    yield benchmark
    del BENCHMARKS["toy"]


def test_a_registered_benchmark_runs_end_to_end(toy_benchmark, tmp_path):
    data = tmp_path / "toy-data"
    data.mkdir()
    out = tmp_path / "toy-run"
    summary = eb.run_benchmark("toy", out, eb.MethodSpec.create("sift"), root=data, dataset_options={"n_pairs": 3})
    assert summary["n_pairs"].item() == 3
    assert summary["mma@3"].item() > 0.8  # SIFT on a moderate warp of a textured scene
    for name in ("config.yaml", "matches.h5", "per_pair.csv", "summary.csv", "mma.png"):
        assert (out / name).is_file(), name
    assert list(pd.read_csv(out / "per_pair.csv")["pair"]) == ["v_toy0/1-2", "v_toy1/1-2", "v_toy2/1-2"]
    # The reports know it too: a table without paper rows (the paper has none for it).
    csv_path, _ = write_table([out], tmp_path / "toy-table")
    table = pd.read_csv(csv_path)
    assert list(table["source"]) == ["measured"] and table["h_acc@3"].item() == summary["h_acc@3"].item()
    with pytest.raises(ValueError, match=r"dataset: .pairs. is not a dataset option of toy \(did you mean .n_pairs.\?\)"):
        eb.run_benchmark("toy", tmp_path / "o", eb.MethodSpec.create("sift"), root=data, dataset_options={"pairs": "x"})


def test_unknown_benchmark_names_the_known_ones():
    with pytest.raises(ValueError, match="hpatches, megadepth, yfcc"):
        eb.get_benchmark("eth3d")


# --------------------------------------------------------------------------- MethodSpec


def test_every_match_changing_field_changes_the_identity(tmp_path):
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"not really weights")
    other = tmp_path / "w2.pth"
    other.write_bytes(b"other bytes")
    base = eb.MethodSpec.create("e3cm", backbone="vgg19", estimator="ransac", max_side=640, seed=0)
    variants = {
        "matcher": eb.MethodSpec.create("direct", backbone="vgg19", max_side=640),
        "backbone": eb.MethodSpec.create("e3cm", backbone="resnet152", estimator="ransac", max_side=640),
        "weights": eb.MethodSpec.create("e3cm", weights=weights, estimator="ransac", max_side=640),
        "estimator": eb.MethodSpec.create("e3cm", estimator="prosac", max_side=640),
        "sampson_px": eb.MethodSpec.create("e3cm", estimator="ransac", sampson_px=(1, 2, 3, 4), max_side=640),
        "ratio": eb.MethodSpec.create("e3cm", estimator="ransac", ratio=(0.8,) * 5, max_side=640),
        "max_side": eb.MethodSpec.create("e3cm", estimator="ransac", max_side=1200),
        "full size": eb.MethodSpec.create("e3cm", estimator="ransac", max_side=None),
        "seed": eb.MethodSpec.create("e3cm", estimator="ransac", max_side=640, seed=1),
    }
    identities = [base.identity()] + [v.identity() for v in variants.values()]
    for name, variant in variants.items():
        assert variant.identity() != base.identity() and variant != base, name
    assert len({repr(i) for i in identities}) == len(identities)
    # Same path, other bytes: the hash tells them apart.
    same_path = eb.MethodSpec.create("e3cm", weights=weights, estimator="ransac", max_side=640)
    weights.write_bytes(b"changed")
    assert eb.MethodSpec.create("e3cm", weights=weights, estimator="ransac", max_side=640) != same_path


def test_what_does_not_change_the_matches_does_not_change_the_identity():
    spec = eb.MethodSpec.create("e3cm", backbone="vgg19", max_side=640, seed=0)
    # The label names a row; it is not part of what was matched.
    assert spec.with_label("my name") == spec and spec.with_label("my name").identity() == spec.identity()
    # top8 draws no random numbers: its matches do not depend on the seed.
    assert eb.MethodSpec.create("e3cm", max_side=640, seed=7).identity() == spec.identity()
    assert eb.MethodSpec.create("sift", seed=3).identity() == eb.MethodSpec.create("sift", seed=0).identity()
    # dfm's stage 0 is a RANSAC: its seed is part of the identity.
    assert eb.MethodSpec.create("dfm", seed=3).identity() != eb.MethodSpec.create("dfm", seed=0).identity()
    # sift has no backbone: a backbone option does not make another method.
    assert eb.MethodSpec.create("sift", backbone="resnet152") == eb.MethodSpec.create("sift")
    # Evaluation settings live elsewhere and are frozen: changing them makes a new EvalSettings.
    ev = eb.EvalSettings()
    assert replace(ev, pose_ransac_px=1.0) != ev and "pose_ransac_px" not in spec.identity()


def test_method_spec_rejects_bad_options_before_any_model_loads(tmp_path):
    with pytest.raises(ValueError, match="ratio"):
        eb.MethodSpec.create("e3cm", ratio=(0.9, 1.5, 0.9, 0.9, 0.9))
    with pytest.raises(ValueError, match="estimator"):
        eb.MethodSpec.create("e3cm", estimator="ransca")
    with pytest.raises(ValueError, match="weights file not found"):
        eb.MethodSpec.create("e3cm", weights=tmp_path / "missing.pth")
    with pytest.raises(ValueError, match="unknown matcher"):
        eb.MethodSpec.create("superglue")


def test_importing_the_package_does_not_load_torch():
    code = "import sys, e3cm_bench, e3cm_bench.storage.cache, e3cm_bench.reporting.tables; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "False", done.stderr
