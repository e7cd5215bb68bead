"""Parity with the reference implementations' outputs, robust to the rounding of features.

A reference file (layout of ../shared/parity: `r09_L{l}_A/B`, `r095_L{l}_A/B`, `r095_casc*`,
`r095_F{l}` (3x3, or OpenCV's stacked 7-point solutions, 6x3 / 9x3), `dfm_A/B`, `dfm_Hinit`)
holds what the E3CM release and the DFM release output on one pair. Rounding of the CNN
features moves with the CPU's kernels and the torch build (measured on VGG19: 3e-7 .. 5.3e-6
of each map's norm between AVX-512, AVX2 and ATen's default kernels; tests/matching/test_parity.py,
docs/methods.md "Parity"), and a match whose ratio or similarity margin sits below that can
flip. So parity is proved in two ways:

- **stage by stage on the reference's own inputs**: each refinement from the reference's
  parent list, the released cascade from the reference's per-level lists (exactly), DFM's
  stage 1 from the reference's stage-0 homography; one flipped match cannot cascade through
  a RANSAC there;
- **end to end with measured ties**: the same computation is repeated on features perturbed
  at the rounding scale (`ROUNDING_SCALE`, twice the largest measured difference); a match
  on which we and the reference disagree is accepted only when the perturbations flip it
  too (ours-only: some perturbed run drops it; reference-only: some perturbed run finds it).
  The 99% / 1% thresholds stay; the accepted ties are counted and printed per list.

Pure functions: maps, cells and point lists in, comparisons out (no file is read here).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from e3cm_bench.matching.release import (
    DFMRelease, dfm_release_final, dfm_release_stage0, dfm_release_stage1, level_points,
    release_cascade, release_dense, release_levels, release_refine,
)

# Noise per map: N(0, 1) scaled to this fraction of the map's RMS, i.e. this relative L2 norm.
# Measured between kernel sets on seed-0 VGG19 (kitti_640): at most 5.3e-6 (ATen default vs
# AVX-512, conv5_3), 2.6e-6 (oneDNN AVX2 vs AVX-512); one thread vs two: 0.
ROUNDING_SCALE = 1e-5
N_PERTURBATIONS = 8
MATCH_TOLERANCE_PX = 1e-3  # a match is the same when all four coordinates agree to this
MIN_SHARED, MAX_EXTRA = 0.99, 0.01  # of the reference's count

TAGS = {"r09": (0.9,) * 5, "r095": (0.9, 0.9, 0.9, 0.9, 0.95)}


def _rows(points0: np.ndarray, points1: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(points0, np.float64).reshape(-1, 2),
                           np.asarray(points1, np.float64).reshape(-1, 2)], 1)


def found_in(rows: np.ndarray, among: np.ndarray) -> np.ndarray:
    """For each row (x0, y0, x1, y1), whether `among` holds it to MATCH_TOLERANCE_PX."""
    from scipy.spatial import cKDTree

    if len(rows) == 0 or len(among) == 0:
        return np.zeros(len(rows), bool)
    distance, _ = cKDTree(among).query(rows, p=np.inf, distance_upper_bound=MATCH_TOLERANCE_PX)
    return np.isfinite(distance)


@dataclass
class ListParity:
    """One list compared with the reference's: counts, and the disagreements accepted as ties."""

    what: str
    n_ref: int
    n_ours: int
    n_both: int
    ties_ref: int = 0  # reference-only matches that a perturbation at the rounding scale finds
    ties_ours: int = 0  # our extra matches that a perturbation drops
    exact: bool = False  # no tie may be accepted (the stage runs on the reference's own inputs)

    @property
    def passed(self) -> bool:
        return (self.n_both + self.ties_ref >= MIN_SHARED * self.n_ref
                and self.n_ours - self.n_both - self.ties_ours <= MAX_EXTRA * max(self.n_ref, 1))

    def line(self) -> str:
        ties = "exact stage" if self.exact else f"ties accepted {self.ties_ref} (reference-only) + {self.ties_ours} (ours-only)"
        return (f"{self.what}: reference {self.n_ref}, ours {self.n_ours}, identical {self.n_both}, {ties}"
                f" -> {'ok' if self.passed else 'FAIL'}")


def compare(what: str, ours: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray],
            perturbed: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> ListParity:
    """Our list against the reference's; with `perturbed` (the same computation on perturbed
    features) the disagreements that the perturbations reproduce are counted as ties."""
    ours_rows, ref_rows = _rows(*ours), _rows(*ref)
    ours_in_ref = found_in(ours_rows, ref_rows)
    ref_in_ours = found_in(ref_rows, ours_rows)
    result = ListParity(what, len(ref_rows), len(ours_rows), int(ref_in_ours.sum()), exact=not perturbed)
    if perturbed:
        runs = [_rows(*p) for p in perturbed]
        ref_only, ours_only = ref_rows[~ref_in_ours], ours_rows[~ours_in_ref]
        reachable = np.zeros(len(ref_only), bool)
        always = np.ones(len(ours_only), bool)
        for run in runs:
            reachable |= found_in(ref_only, run)
            always &= found_in(ours_only, run)
        result.ties_ref, result.ties_ours = int(reachable.sum()), int((~always).sum())
    return result


def perturb(maps: Sequence[torch.Tensor], seed: int, scale: float = ROUNDING_SCALE) -> list[torch.Tensor]:
    """Each map plus N(0, 1) noise of `scale` times its RMS, drawn on the CPU in float32."""
    generator = torch.Generator().manual_seed(seed)
    out = []
    for m in maps:
        rms = float(m.double().square().mean().sqrt())
        noise = torch.randn(m.shape, generator=generator, dtype=torch.float32).mul_(scale * rms)
        out.append(m + noise.to(m.dtype).to(m.device))
    return out


def under_perturbation(run: Callable[..., object], maps: Sequence[Sequence[torch.Tensor]], n: int = N_PERTURBATIONS,
                       scale: float = ROUNDING_SCALE) -> list:
    """`run(*maps)` repeated on n perturbed copies (seeds 1..n; each list of maps its own draw)."""
    return [run(*[perturb(m, 1000 * k + i, scale) for i, m in enumerate(maps)]) for k in range(1, n + 1)]


def to_cells(points: np.ndarray, level: int) -> torch.Tensor:
    """Pixel coordinates of `level` -> its cells (inverse of release.level_points)."""
    return torch.from_numpy(np.rint((np.asarray(points, np.float64) + 0.5) / 2**level - 0.5).astype(np.int64))


# --------------------------------------------------------------------------- the E3CM release


def _points(cells: Sequence[torch.Tensor]) -> list[np.ndarray]:
    top = len(cells) - 1
    return [level_points(c, top - i) for i, c in enumerate(cells)]


def release_lists(maps0: list[torch.Tensor], maps1: list[torch.Tensor], ratio: tuple[float, ...]) -> list[tuple]:
    """The release's per-level point lists (deepest first) as (points0, points1) pairs."""
    cells0, cells1 = release_levels(maps0, maps1, ratio)
    return list(zip(_points(cells0), _points(cells1)))


def release_levels_end_to_end(maps0, maps1, ref: dict, tag: str, n: int = N_PERTURBATIONS) -> list[ListParity]:
    """Our chained levels (dense at the deepest map, refinement down to level 0) against the
    reference's lists `{tag}_L{l}`, ties measured by perturbing every map."""
    ratio = TAGS[tag]
    ours = release_lists(maps0, maps1, ratio)
    perturbed = under_perturbation(lambda a, b: release_lists(a, b, ratio), [maps0, maps1], n)
    top = len(maps0) - 1
    return [compare(f"{tag}_L{top - i}", ours[i], (ref[f"{tag}_L{top - i}_A"], ref[f"{tag}_L{top - i}_B"]),
                    [p[i] for p in perturbed]) for i in range(len(ours))]


def release_levels_by_stage(maps0, maps1, ref: dict, tag: str, n: int = N_PERTURBATIONS) -> list[ListParity]:
    """Each stage on the reference's own input: the deepest level's dense matching, then each
    refinement from the reference's parent list; ties measured per stage."""
    ratio = TAGS[tag]
    top = len(maps0) - 1

    def dense(a, b):  # each stage gets (and perturbs) only the maps it reads
        c0, c1 = release_dense(a[0], b[0], ratio[top])
        return level_points(c0, top), level_points(c1, top)

    used = [[maps0[top]], [maps1[top]]]
    out = [compare(f"{tag}_L{top} dense", dense(*used), (ref[f"{tag}_L{top}_A"], ref[f"{tag}_L{top}_B"]),
                   under_perturbation(dense, used, n))]
    for level in range(top - 1, -1, -1):
        parents0, parents1 = (to_cells(ref[f"{tag}_L{level + 1}_{s}"], level + 1) for s in "AB")

        def refine(a, b, level=level, parents0=parents0, parents1=parents1):
            c0, c1 = release_refine(a[0], b[0], parents0, parents1, ratio[level], "own", dedup=True)
            return level_points(c0, level), level_points(c1, level)

        used = [[maps0[level]], [maps1[level]]]
        out.append(compare(f"{tag}_L{level} from reference L{level + 1}", refine(*used),
                           (ref[f"{tag}_L{level}_A"], ref[f"{tag}_L{level}_B"]),
                           under_perturbation(refine, used, n)))
    return out


def release_cascade_from_reference(ref: dict, tag: str, levels: int = 5) -> tuple[list[ListParity], dict]:
    """The released cascade run on the reference's own per-level lists: its result (and, where
    the file holds them, every level's survivors and F) must be the reference's exactly."""
    top = levels - 1
    points0 = [ref[f"{tag}_L{top - i}_A"] for i in range(levels)]
    points1 = [ref[f"{tag}_L{top - i}_B"] for i in range(levels)]
    cv2.setRNGSeed(0)
    out = release_cascade(points0, points1)
    checks = [compare(f"{tag} cascade from reference lists", (out["points0"], out["points1"]),
                      (ref[f"{tag}_casc_A"], ref[f"{tag}_casc_B"]))]
    for i, survivors in out["survivors"].items():
        level = top - i
        if f"{tag}_cascL{level}_A" in ref:
            checks.append(compare(f"{tag} cascade L{level} survivors", survivors,
                                  (ref[f"{tag}_cascL{level}_A"], ref[f"{tag}_cascL{level}_B"])))
    return checks, out


# A reference F is what OpenCV's findFundamentalMat returned: 3 x 3, or, from exactly 7
# matches, every real solution of its 7-point algorithm stacked (6 x 3 or 9 x 3), of which
# the release used the first (matching/release.py).
F_ROWS = (3, 6, 9)


def _shape(array: np.ndarray) -> str:
    return "x".join(str(n) for n in array.shape) or "scalar"


def reference_fundamental(ref: dict, key: str) -> np.ndarray:
    """The F the release used at `key`: the first 3 rows of what the file holds. A ValueError
    naming the key and its shape where that is not 3 x 3, 6 x 3 or 9 x 3."""
    F = np.asarray(ref[key])
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] not in F_ROWS:
        raise ValueError(f"{key}: shape {_shape(F)}, not a fundamental matrix (3x3) nor OpenCV's stacked "
                         f"7-point solutions (6x3, 9x3)")
    return F[:3]


def check_reference(ref: dict) -> None:
    """A ValueError, one line naming the key and its shape, for the first array of `ref` that
    the checks could not read: an F (`{tag}_F{l}`) other than 3x3 / 6x3 / 9x3, a homography
    (`*_Hinit`, `dfm_H`) other than 3x3, a point list (`*_A`, `*_B`) other than N x 2 or of
    another length than its partner. Keys the checks do not read are left alone."""
    for key in sorted(ref):
        value = np.asarray(ref[key])
        if re.fullmatch(rf"({'|'.join(TAGS)})_F\d+", key):
            reference_fundamental(ref, key)
        elif key.endswith("_Hinit") or key == "dfm_H":
            if value.shape != (3, 3):
                raise ValueError(f"{key}: shape {_shape(value)}, not a homography (3x3)")
        elif key.endswith(("_A", "_B")):
            if value.ndim != 2 or value.shape[1] != 2:
                raise ValueError(f"{key}: shape {_shape(value)}, not a point list (N x 2)")
            partner = key[:-1] + ("B" if key.endswith("_A") else "A")
            if partner in ref and len(np.asarray(ref[partner])) != len(value):
                rows = len(np.asarray(ref[partner]))
                raise ValueError(f"{key}: shape {_shape(value)}, but {partner} has {rows} rows")


def fundamental_differences(out: dict, ref: dict, tag: str, levels: int = 5) -> dict[int, float]:
    """Largest |F_ours - F_ref| per level where the file holds the reference's F (a level
    whose RANSAC found none has no F on either side: its key is absent from the file). A
    reference F of OpenCV's stacked 7-point solutions is compared by its first solution,
    the one the release used; one of a shape nobody returns raises a ValueError naming it."""
    top = levels - 1
    return {top - i: float(np.abs(F - reference_fundamental(ref, f"{tag}_F{top - i}")).max())
            for i, F in out["fundamentals"].items() if F is not None and f"{tag}_F{top - i}" in ref}


F_RTOL = 1e-9  # the same OpenCV call on the same list: the same F up to rounding, relative to its largest entry


def fundamental_mismatches(out: dict, ref: dict, tag: str, levels: int = 5) -> list[str]:
    """Where our F (the cascade run on the reference's lists) is not the reference's: an F on
    one side only (a different cascade), or one further than F_RTOL of the reference's
    largest entry from the solution the release used. Empty when every F agrees."""
    top = levels - 1
    differences = fundamental_differences(out, ref, tag, levels)
    problems = []
    for i, F in out["fundamentals"].items():
        key = f"{tag}_F{top - i}"
        if (F is None) != (key not in ref):
            problems.append(f"{key}: {'the reference' if F is None else 'ours'} only")
        elif F is not None and differences[top - i] > F_RTOL * np.abs(reference_fundamental(ref, key)).max():
            problems.append(f"{key}: max |F - F_ref| = {differences[top - i]:.3g}")
    return problems


# --------------------------------------------------------------------------- the DFM release


H_RTOL = 1e-6  # OpenCV's findHomography on the same list rounds differently per CPU (measured 2.4e-7)
# ... and by more where its last step, a Levenberg-Marquardt refinement over the RANSAC inliers,
# stops before the last bits settle: its linear solves go through the LAPACK of the OpenBLAS in
# OpenCV's wheel, whose kernels OpenBLAS picks per CPU (Haswell's on an AMD EPYC, SkylakeX's on an
# Intel Xeon). On leuven 1-3 (640 px, 164 stage-0 matches, 140 inliers whatever the kernel) H[1,0]
# differs by 1.9e-6 of itself between those two kernels, yet no pixel moves by more than 8e-6 px
# (tests/matching/test_parity_stage0.py). H_init is only ever used to warp B, so two H_init are the
# same when they put every pixel of B within MATCH_TOLERANCE_PX of each other.
H_TOLERANCE_PX = MATCH_TOLERANCE_PX
GRID_STEP_PX = 8  # spacing of the pixels at which two homographies are compared (plus the far edges)


def homography_distance_px(H_a: np.ndarray, H_b: np.ndarray, width: int, height: int) -> float:
    """Largest distance between where H_a and H_b map a pixel of a width x height image (a grid of
    GRID_STEP_PX and the last row and column); inf where either sends a pixel to infinity."""
    xs = np.unique(np.r_[np.arange(0, width, GRID_STEP_PX), width - 1])
    ys = np.unique(np.r_[np.arange(0, height, GRID_STEP_PX), height - 1])
    gx, gy = np.meshgrid(xs, ys)
    points = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)]).astype(np.float64)
    mapped = []
    for H in (H_a, H_b):
        q = np.asarray(H, np.float64) @ points
        if not (np.all(q[2] > 1e-12) or np.all(q[2] < -1e-12)):  # the image holds H's line at infinity
            return float("inf")
        mapped.append(q[:2] / q[2])
    distance = float(np.abs(mapped[0] - mapped[1]).max())
    return distance if np.isfinite(distance) else float("inf")


def dfm_stage0(top0: torch.Tensor, top1: torch.Tensor, level: int, ref: dict, n: int = N_PERTURBATIONS) -> dict:
    """Stage 0 (mutual NN at the deepest map + homography RANSAC) against the reference's
    H_init: equal to H_RTOL or, where the entries differ more, moving no pixel of B (the padded
    map's extent) by more than H_TOLERANCE_PX (`H_px`: by how much; the reason is OpenCV's
    refinement rounding per OpenBLAS kernel, see H_TOLERANCE_PX); or different through a
    measured tie (a perturbation at the rounding scale changes the stage-0 list; stage 1 is
    then proved from the reference's H)."""
    settings = DFMRelease()
    H, n0 = dfm_release_stage0(top0, top1, level, settings)
    height, width = (side * 2**level for side in top1.shape[-2:])
    distance = homography_distance_px(H, ref["dfm_Hinit"], width, height)
    entries = bool(np.allclose(H, ref["dfm_Hinit"], rtol=H_RTOL, atol=1e-9))
    same = entries or distance <= H_TOLERANCE_PX
    result = {"H": H, "stage0_matches": n0, "same_H": same, "tie": False, "H_px": distance,
              "same_entries": entries}
    if not same:
        base = release_dense(top0, top1, settings.stage0_ratio)
        for a, b in under_perturbation(lambda a, b: (a, b), [[top0], [top1]], n):
            cells = release_dense(a[0], b[0], settings.stage0_ratio)
            if len(cells[0]) != len(base[0]) or not all(torch.equal(x, y) for x, y in zip(cells, base)):
                result["tie"] = True
                break
    return result


def dfm_stage1(pyramid: Callable[[np.ndarray], tuple[list[torch.Tensor], torch.Tensor | None]],
               image0: np.ndarray, image1: np.ndarray, H: np.ndarray, ref: dict, what: str,
               n: int | None = N_PERTURBATIONS) -> tuple[ListParity, tuple[np.ndarray, np.ndarray]]:
    """DFM's stage 1 and final filter on B warped by H (the reference's own H_init proves the
    stage; the matcher's H gives the end-to-end list), against the reference's dfm_A/B with
    ties measured. `pyramid` maps an RGB image to (maps, stage-1 map or None) as the DFM
    matcher's backbone does. Returns the comparison and our list."""
    settings = DFMRelease()
    warped = cv2.warpPerspective(image1, H, (image0.shape[1], image0.shape[0]))
    feats0, top0 = pyramid(image0)
    feats_w, top_w = pyramid(warped)
    top0 = feats0[-1] if top0 is None else top0
    top_w = feats_w[-1] if top_w is None else top_w
    size0, size1 = (image0.shape[1], image0.shape[0]), (image1.shape[1], image1.shape[0])

    def stage1(a, b):
        cells0, cells_w = dfm_release_stage1(a[:-1], b[:-1], a[-1], b[-1], settings)
        x0, x1, _ = dfm_release_final(cells0, cells_w, H, size0, size1, settings)
        return x0, x1

    maps0, maps_w = [*feats0, top0], [*feats_w, top_w]
    ours = stage1(maps0, maps_w)
    n = N_PERTURBATIONS if n is None else n
    return compare(what, ours, (ref["dfm_A"], ref["dfm_B"]), under_perturbation(stage1, [maps0, maps_w], n)), ours


__all__ = [
    "ListParity", "ROUNDING_SCALE", "N_PERTURBATIONS", "TAGS", "compare", "perturb", "under_perturbation", "to_cells",
    "release_lists", "release_levels_end_to_end", "release_levels_by_stage", "release_cascade_from_reference",
    "fundamental_differences", "reference_fundamental", "check_reference", "F_ROWS",
    "F_RTOL", "fundamental_mismatches", "dfm_stage0", "dfm_stage1", "H_RTOL", "H_TOLERANCE_PX", "homography_distance_px",
]
