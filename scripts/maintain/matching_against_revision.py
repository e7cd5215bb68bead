"""The work after the backbone as the code is now against an earlier revision's, side by side.

    python scripts/maintain/matching_against_revision.py --against REV [--precision bf16] [--size 640x480 --size 1200x900] [--repeat 3]

`e3cm` (top-8) on VGG19 with random weights (seed 0) and pair_speed.py's synthetic pair. The
backbone runs once per size; then match_pyramids runs on the same pyramids, alternating
between the matching package of revision REV (e3cm_bench/matching and geometry.py, read with
`git archive` into a temporary folder and imported under another name) and the current one.
Both get the matcher's memo (DeepMatcher.image_product, without a feature cache): what a
revision asks of it by name is computed, except the level-0 pixel rows the backbone's pass
kept, which the current code reads instead of a normalised copy of level 0.
For each it prints the median time after the backbone, over the backbone's own time, with
the stages; and whether both gave the same matches bit for bit.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import shutil
import io
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import torch

from e3cm_bench.ground.machine import cpu_info, cpu_isa
from e3cm_bench.matching import pipeline
from e3cm_bench.method.spec import MethodSpec

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "measure"))
from pair_speed import add_allocator_option, synthetic_pair, use_allocator  # noqa: E402


def pipeline_of(rev: str, folder: Path):
    """REV's matching/pipeline.py, imported as e3cm_bench_rev.matching.pipeline from `folder`."""
    root = Path(__file__).resolve().parents[2]
    archive = subprocess.run(["git", "-C", str(root), "archive", rev, "e3cm_bench/matching", "e3cm_bench/geometry/two_view.py"],
                             capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    package = folder / "e3cm_bench_rev"
    (folder / "e3cm_bench").rename(package)
    (package / "__init__.py").write_text("")
    sys.path.insert(0, str(folder))
    return importlib.import_module("e3cm_bench_rev.matching.pipeline")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", required=True, help="a git revision")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
    parser.add_argument("--size", action="append", default=None)
    parser.add_argument("--repeat", type=int, default=3)
    add_allocator_option(parser)
    args = parser.parse_args()
    allocator = use_allocator(args.allocator)
    folder = Path(tempfile.mkdtemp())
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    earlier = pipeline_of(args.against, folder)
    ways = {args.against: earlier, "current": pipeline}
    torch.manual_seed(0)
    options = {} if args.precision == "fp32" else {"precision": args.precision}
    matcher = MethodSpec.create("e3cm", "vgg19", options=options).build("cpu", pretrained=False)
    print(f"CPU {cpu_info()[0]} ({cpu_isa()}); torch {torch.__version__}, {torch.get_num_threads()} threads; "
          f"e3cm, VGG19 (random weights, seed 0), {args.precision}; median of {args.repeat}; allocator {allocator}")
    for size in args.size or ["640x480", "1200x900"]:
        w, h = (int(v) for v in size.split("x"))
        image0, image1 = synthetic_pair(w, h)
        backbone = []
        for _ in range(2):
            t = time.perf_counter()
            feats0, feats1, _ = matcher.pyramids(image0, image1)
            backbone.append(time.perf_counter() - t)
        timings = {name: [] for name in ways}
        outputs = {}
        for _ in range(args.repeat + 1):  # the first round warms up
            for name, module in ways.items():
                outputs[name] = module.match_pyramids(feats0, feats1, (w, h), (w, h), matcher.settings,
                                                      memo=matcher.image_product)
                timings[name].append(outputs[name]["timings"])
        same = all(torch.equal(torch.as_tensor(outputs[args.against][k]), torch.as_tensor(outputs["current"][k]))
                   for k in ("keypoints0", "keypoints1", "scores"))
        seconds = min(backbone)
        print(f"{size}: backbone {seconds:.2f} s (2 images, best of 2); {len(outputs['current']['keypoints0'])} matches; "
              f"the same bit for bit: {same}")
        for name, runs in timings.items():
            runs = runs[1:]
            stage = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            after = statistics.median(sum(r.values()) for r in runs)
            refine = sum(v for k, v in stage.items() if k.startswith("refine"))
            print(f"  {name}: after the backbone {after:.3f} s = {after / seconds:.2f} of the backbone; normalise "
                  f"{stage['normalise']:.3f}, initial {stage['initial']:.3f}, cascade {stage['cascade']:.3f}, "
                  f"refinement {refine:.3f}", flush=True)


if __name__ == "__main__":
    main()
