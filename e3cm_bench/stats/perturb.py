"""Perturbations at the scale of a CPU's rounding: how the regression gate's noise ensemble
(gate/ensemble.py) reruns a run as another machine might have run it.

Two stages of a run round differently on another CPU, and each is perturbed at its own scale
while a `Perturbation` is active (docs/results.md "Noise model" says how they were found):

- **the CNN features**: each backbone stage's output gets Gaussian noise of ``feature_scale``
  times the map's RMS (parity.ROUNDING_SCALE: kernel sets differ by up to 5.3e-6 of a map's
  norm). The noise is added before the next stage reads the map, so it travels as rounding does.
- **the robust estimators' linear algebra**: OpenCV solves its RANSAC models through OpenBLAS,
  whose kernels are picked per CPU; a last-bit change in a model flips an inlier count or a
  tie between hypotheses, and the RANSAC then ends elsewhere. The points every estimator in
  geometry.py receives are moved by ``point_scale`` of their magnitude (the float32 rounding
  step: OpenCV casts the points to float32 before it fits), and their order is shuffled,
  since a RANSAC whose arithmetic differs in one bit may take another path (see
  perturb_correspondences).

Outside a `perturbed` block every function here is the identity, so nothing changes for a
normal run. Each perturbation is seeded by the draw and by the bytes it perturbs, so a draw
gives the same values whatever order its pairs run in, and a resumed ensemble the same as an
uninterrupted one.
"""

from __future__ import annotations

from collections.abc import Iterator
import zlib
from contextlib import contextmanager
from dataclasses import dataclass

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is imported where maps are perturbed: geometry.py, which needs none, imports this module
    import torch

FEATURE_SCALE = 1e-5
POINT_SCALE = float(np.finfo(np.float32).eps)


@dataclass(frozen=True)
class Perturbation:
    """One draw of the noise ensemble: its seed and the scale of each perturbed stage."""

    draw: int
    feature_scale: float = FEATURE_SCALE
    point_scale: float = POINT_SCALE

    def describe(self) -> dict:
        return {"draw": self.draw, "feature_scale": self.feature_scale, "point_scale": self.point_scale}


class _State:
    """The active draw (one module-level state: the match stage runs in one thread, and the
    perturbed stages are deep inside it)."""

    perturbation: Perturbation | None = None


_STATE = _State()


@contextmanager
def perturbed(perturbation: Perturbation) -> Iterator[Perturbation]:
    """Run the block as draw ``perturbation.draw`` of the ensemble; nesting is refused."""
    if _STATE.perturbation is not None:
        raise RuntimeError("a perturbation is already active")
    _STATE.perturbation = perturbation
    try:
        yield perturbation
    finally:
        _STATE.perturbation = None


def _seed(draw: int, stage: int, *arrays: np.ndarray) -> list[int]:
    """A seed from the draw, the stage and the bytes of what is perturbed."""
    return [draw, stage, *(zlib.crc32(np.ascontiguousarray(a).tobytes()) for a in arrays)]


def active() -> Perturbation | None:
    return _STATE.perturbation


def perturb_map(x: torch.Tensor) -> torch.Tensor:
    """x plus Gaussian noise at feature_scale of its RMS (per image of a batch); x itself when
    no perturbation is active."""
    p = _STATE.perturbation
    if p is None or p.feature_scale <= 0:
        return x
    # empty_like keeps x's memory format (channels_last maps stay so: their pixel rows are read)
    import torch

    values = x.detach().float().cpu()
    generator = torch.Generator().manual_seed(
        int(np.random.SeedSequence(_seed(p.draw, 1, values.numpy())).generate_state(1)[0])
    )
    noise = torch.empty_like(x, dtype=torch.float32, device="cpu").normal_(generator=generator).to(x.device)
    rms = x.float().pow(2).mean(dim=tuple(range(1, x.dim())), keepdim=True).sqrt()
    return x + (noise * (p.feature_scale * rms)).to(x.dtype)


def perturb_correspondences(x0: np.ndarray, x1: np.ndarray, keep_order: bool = False
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(x0, x1, order) as a robust estimator should see them in this draw: both N x 2 point
    sets moved by point_scale of their magnitude (uniform in [-1, 1] of it, per coordinate)
    and, unless keep_order (PROSAC reads the order as a ranking), shuffled by ``order``; the
    inputs themselves and None when no perturbation is active.

    The shuffle stands for what another CPU does to a RANSAC: once one input or one model
    differs in its last bit, the estimator walks another path through its samples, so each
    draw gives every RANSAC a sample sequence of its own."""
    p = _STATE.perturbation
    x0, x1 = np.asarray(x0), np.asarray(x1)
    if p is None or len(x0) == 0:
        return x0, x1, None
    rng = np.random.default_rng(_seed(p.draw, 2, x0, x1))
    moved = []
    for points in (x0, x1):
        step = p.point_scale * np.maximum(np.abs(points), 1.0)
        moved.append(points + step * rng.uniform(-1.0, 1.0, points.shape))
    order = None if keep_order else rng.permutation(len(x0))
    if order is not None:
        moved = [m[order] for m in moved]
    return moved[0], moved[1], order
