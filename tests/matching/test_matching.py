"""The E3CM matching steps (e3cm_bench.matching) on hand-made and synthetic feature maps."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from e3cm_bench.geometry import two_view as geometry
from e3cm_bench.matching.cascade import (UnitPixels, confidence_scores, epipolar_inliers, estimate_level_fundamental,
                                         pixel_norms, pixel_rows)
from e3cm_bench.matching.dense import match_dense_level, mutual_nn_ratio
from e3cm_bench.matching.levels import cell_centres, inside, valid_extent
from e3cm_bench.matching.pipeline import DEFAULT_SAMPSON_PX, E3CMSettings, match_pyramids
from e3cm_bench.matching.refine import ChildTest, refine_to_children


def unit_rows(x) -> torch.Tensor:
    return F.normalize(torch.as_tensor(x, dtype=torch.float64), dim=-1)


def random_map(c: int, h: int, w: int, gen: torch.Generator) -> torch.Tensor:
    return F.normalize(torch.randn(c, h, w, generator=gen, dtype=torch.float64), dim=0)


def angle_vec(dims: int, i: int, j: int, degrees: float) -> list[float]:
    """Unit vector at `degrees` in the plane of axes i, j."""
    v = [0.0] * dims
    v[i] = math.cos(math.radians(degrees))
    v[j] = math.sin(math.radians(degrees))
    return v


# --------------------------------------------------------------------------- levels


def test_cell_centres_and_valid_extent():
    cells = torch.tensor([[0, 0], [3, 1]])
    # level 0: the cell is the pixel; level 2: ((x + 0.5) * 4 - 0.5)
    np.testing.assert_allclose(cell_centres(cells, 0).numpy(), [[0, 0], [3, 1]])
    np.testing.assert_allclose(cell_centres(cells, 2).numpy(), [[1.5, 1.5], [13.5, 5.5]])
    # 131 x 97 image: level 0 131 x 97 cells; level 4 (stride 16): centres 7.5 + 16 k <= 130
    # -> k <= 7.66 -> 8 columns; rows: 7.5 + 16 k <= 96 -> k <= 5.53 -> 6 rows.
    assert valid_extent((131, 97), 0) == (131, 97)
    assert valid_extent((131, 97), 4) == (8, 6)
    assert valid_extent((128, 96), 4) == (8, 6)
    mask = inside(torch.tensor([[0, 0], [1, 1], [6, 4], [7, 4], [6, 5]]), (8, 6), margin=1)
    assert mask.tolist() == [False, True, True, False, False]


# --------------------------------------------------------------------------- confidence (Eq. 3)


def test_confidence_level1_by_hand():
    # Level 1: 2 x 2 patches, pixel order k = (0,0), (1,0), (0,1), (1,1) -> k = 2 y + x.
    # A's patch holds the unit axes e0..e3 (C = 4), so sim[i, j] = A_i . B_j = B_j[i].
    #   B_0 = (0.8, 0.6, 0, 0)     B_1 = (0.6, 0, 0.8, 0)
    #   B_2 = (0, 0, 0.96, 0.28)   B_3 = (0.28, 0.96, 0, 0)
    # sim (rows i = A pixels, columns j = B pixels):
    #   i=0: 0.80 0.60 0.00 0.28 -> argmax 0
    #   i=1: 0.60 0.00 0.00 0.96 -> argmax 3
    #   i=2: 0.00 0.80 0.96 0.00 -> argmax 2
    #   i=3: 0.00 0.00 0.28 0.00 -> argmax 2
    # column argmax: j=0 -> 0, j=1 -> 2, j=2 -> 2, j=3 -> 1
    # mutual on the diagonal: k=0 (0<->0) and k=2 (2<->2); k=1 (row -> 3) and k=3 (row -> 2) not.
    # d_00 = 1 - 0.8 = 0.2, d_22 = 1 - 0.96 = 0.04 -> c = 1/0.2 + 1/0.04 = 5 + 25 = 30.
    gen = torch.Generator().manual_seed(0)
    fa = random_map(4, 4, 4, gen)
    fb = random_map(4, 4, 4, gen)
    A = torch.eye(4, dtype=torch.float64)
    B = unit_rows([[0.8, 0.6, 0, 0], [0.6, 0, 0.8, 0], [0, 0, 0.96, 0.28], [0.28, 0.96, 0, 0]])
    # A's match sits in level-1 cell (1, 0): pixels x 2..3, y 0..1; B's in cell (0, 1): x 0..1, y 2..3.
    for k in range(4):
        fa[:, k // 2, 2 + k % 2] = A[k]
        fb[:, 2 + k // 2, k % 2] = B[k]
    # Second match: identical patches, every pixel mutual with d = 0, floored at eps:
    # c = 4 / eps = 4000 for eps = 1e-3, 400 for eps = 1e-2.
    # A cell (0, 1) and B cell (1, 0).
    for k in range(4):
        fb[:, k // 2, 2 + k % 2] = fa[:, 2 + k // 2, k % 2]
    cells0 = torch.tensor([[1, 0], [0, 1]])
    cells1 = torch.tensor([[0, 1], [1, 0]])
    c = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), cells0, cells1, level=1)
    np.testing.assert_allclose(c.numpy(), [30.0, 4000.0], rtol=1e-9)
    c = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), cells0, cells1, level=1, eps=1e-2)
    np.testing.assert_allclose(c.numpy(), [30.0, 400.0], rtol=1e-9)
    # Matches are scored independently: order and chunking (tiny budget) do not matter.
    c = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), cells0.flip(0), cells1.flip(0), level=1, budget=1)
    np.testing.assert_allclose(c.numpy(), [4000.0, 30.0], rtol=1e-9)
    # float32 maps give the same numbers to float precision.
    c32 = confidence_scores(UnitPixels.of(fa.float()), UnitPixels.of(fb.float()), cells0, cells1, level=1)
    np.testing.assert_allclose(c32.numpy(), [30.0, 4000.0], rtol=1e-4)


def test_confidence_level2_by_hand():
    # Level 2: 4 x 4 patches, 16 pixels, k = 4 y + x; A's pixels are the axes e0..e15 (C = 16).
    # B_k = 0.8 e_k + 0.6 e_(k+1 mod 16): column k peaks at row k (0.8 > 0.6), row i has
    # B_i[i] = 0.8 > B_(i-1)[i] = 0.6 -> every pixel mutual, d = 0.2 each -> c = 16 * 5 = 80.
    # Then B_5 = 0.28 e5 + 0.96 e9: column 5 peaks at row 9 -> pixel 5 not mutual; row 9 now
    # peaks at column 5 (0.96 > B_9[9] = 0.8) -> pixel 9 not mutual either. Rows 4, 6, 10 are
    # unaffected (0.8 on their diagonal beats 0.6 / 0.28 / 0). 14 mutual -> c = 14 * 5 = 70.
    gen = torch.Generator().manual_seed(1)
    fa = random_map(16, 8, 8, gen)
    fb = random_map(16, 8, 8, gen)
    A = torch.eye(16, dtype=torch.float64)
    B = torch.stack([unit_rows(angle_vec(16, k, (k + 1) % 16, math.degrees(math.atan2(0.6, 0.8)))) for k in range(16)])
    for k in range(16):  # A: cell (1, 1) = pixels 4..7; B: cell (0, 1) = x 0..3, y 4..7
        fa[:, 4 + k // 4, 4 + k % 4] = A[k]
        fb[:, 4 + k // 4, k % 4] = B[k]
    c = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), torch.tensor([[1, 1]]), torch.tensor([[0, 1]]), level=2)
    np.testing.assert_allclose(c.numpy(), [80.0], rtol=1e-9)
    fb[:, 4 + 5 // 4, 5 % 4] = unit_rows([0.28 if i == 5 else 0.96 if i == 9 else 0.0 for i in range(16)])
    c = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), torch.tensor([[1, 1]]), torch.tensor([[0, 1]]), level=2)
    np.testing.assert_allclose(c.numpy(), [70.0], rtol=1e-9)


@pytest.mark.parametrize("level", [1, 2, 3, 4])
def test_confidence_top_k_is_exact_and_skips_most_matches(level):
    # Smooth random maps; B is A shifted by whole cells plus noise, so the true matches are
    # confident and the random ones are not. Asking for the top 8 must give the same 8
    # matches (ties broken by index, as the cascade's stable argsort does) and the same
    # scores as scoring every match, while leaving some matches unscored (-inf).
    gen = torch.Generator().manual_seed(level)
    side = 2**level
    cells_w, cells_h = 12, 10
    smooth = F.avg_pool2d(torch.randn(1, 32, cells_h * side + 4, cells_w * side + 4, generator=gen), 5, 1)[0]
    fa = F.normalize(smooth, dim=0)
    shift = 2  # cells
    fb = torch.roll(fa, shifts=shift * side, dims=2) + 0.3 * torch.randn(fa.shape, generator=gen)
    fb = F.normalize(fb, dim=0)
    xs, ys = torch.meshgrid(torch.arange(cells_w - shift), torch.arange(cells_h), indexing="xy")
    true0 = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
    true1 = true0 + torch.tensor([shift, 0])
    wrong0 = torch.stack([torch.randint(0, cells_w, (150,), generator=gen), torch.randint(0, cells_h, (150,), generator=gen)], 1)
    wrong1 = torch.stack([torch.randint(0, cells_w, (150,), generator=gen), torch.randint(0, cells_h, (150,), generator=gen)], 1)
    perm = torch.randperm(len(true0) + 150, generator=gen)
    cells0, cells1 = torch.cat([true0, wrong0])[perm], torch.cat([true1, wrong1])[perm]
    full = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), cells0, cells1, level)
    top = confidence_scores(UnitPixels.of(fa), UnitPixels.of(fb), cells0, cells1, level, top=8)
    want = np.argsort(-full.numpy(), kind="stable")[:8]
    got = np.argsort(-top.numpy(), kind="stable")[:8]
    np.testing.assert_array_equal(got, want)
    assert torch.equal(top[want], full[want])
    scored = torch.isfinite(top)
    assert torch.equal(top[scored], full[scored])
    assert scored.sum() < len(cells0), "no match was ruled out by its bound"


# --------------------------------------------------------------------------- mutual NN + ratio


def hand_descriptors():
    """Groups in orthogonal planes (cross-group cosine 0, distance 1):

    g1 (axis 0):      a0 = b0 = e0                  -> mutual, d = 0 < 0.9 * 1: KEPT
    g2 (axes 1, 2):   a1 at 0 deg; b1 at 30, b2 at -31 deg
        a1: d(b1) = 1 - cos 30 = 0.1340, d(b2) = 1 - cos 31 = 0.1428; ratio 0.938 > 0.9
        b1's nearest is a1 (only A vector in the plane) -> mutual but FAILS the ratio (A side)
    g3 (axes 3, 4):   a2 at 0, a3 at 40 deg; b3 at 20.2 deg
        b3: d(a3) = 1 - cos 19.8 = 0.0591, d(a2) = 1 - cos 20.2 = 0.0615 -> nearest a3, ratio 0.961
        a3: nearest b3, second 1 (other planes) -> mutual, passes A side, FAILS B side
    g4 (axes 5, 6):   a4 at 0; b4 at 10, b5 at 25 deg
        a4: d(b4) = 0.0152, d(b5) = 0.0937 -> ratio 0.162; b4: nearest a4, second 1: KEPT
        b5's nearest is a4, whose nearest is b4: not mutual
    """
    d = 7
    A = unit_rows([angle_vec(d, 0, 1, 0), angle_vec(d, 1, 2, 0), angle_vec(d, 3, 4, 0), angle_vec(d, 3, 4, 40), angle_vec(d, 5, 6, 0)])
    B = unit_rows(
        [angle_vec(d, 0, 1, 0), angle_vec(d, 1, 2, 30), angle_vec(d, 1, 2, -31), angle_vec(d, 3, 4, 20.2),
         angle_vec(d, 5, 6, 10), angle_vec(d, 5, 6, 25)]
    )
    return A, B


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_mutual_nn_ratio_hand_made(dtype):
    A, B = hand_descriptors()
    A, B = A.to(dtype), B.to(dtype)
    i0, i1, dist = mutual_nn_ratio(A, B, 0.9)
    assert i0.tolist() == [0, 4] and i1.tolist() == [0, 4]
    np.testing.assert_allclose(dist.double().numpy(), [0.0, 1 - math.cos(math.radians(10))], atol=1e-6)
    # 0.95 admits g2 (0.938); g3 (0.961) still fails; 0.97 admits it too.
    i0, i1, _ = mutual_nn_ratio(A, B, 0.95)
    assert i0.tolist() == [0, 1, 4] and i1.tolist() == [0, 1, 4]
    i0, i1, _ = mutual_nn_ratio(A, B, 0.97)
    assert i0.tolist() == [0, 1, 3, 4] and i1.tolist() == [0, 1, 3, 4]
    # Swapping the roles swaps the result.
    j1, j0, _ = mutual_nn_ratio(B, A, 0.97)
    assert sorted(zip(j0.tolist(), j1.tolist())) == [(0, 0), (1, 1), (3, 3), (4, 4)]
    # Chunking (1 row at a time) changes nothing.
    k0, k1, _ = mutual_nn_ratio(A, B, 0.97, chunk=1)
    assert k0.tolist() == [0, 1, 3, 4] and k1.tolist() == [0, 1, 3, 4]


def test_mutual_nn_ratio_ties_and_edge_sizes():
    A, B = hand_descriptors()
    # Two identical candidates: best == second, 0 < 0.9 * 0 is false -> ambiguous, dropped.
    i0, _, _ = mutual_nn_ratio(A[:1], torch.cat([B[:1], B[:1]]), 0.9)
    assert len(i0) == 0
    # A single candidate on one side: its runner-up is absent (infinite distance), so the
    # ratio passes on that side.
    i0, i1, _ = mutual_nn_ratio(A, B[4:5], 0.9)
    assert i0.tolist() == [4] and i1.tolist() == [0]
    i0, i1, _ = mutual_nn_ratio(A[:1], B[:1], 0.9)
    assert i0.tolist() == [0] and i1.tolist() == [0]
    for a, b in ((A[:0], B), (A, B[:0])):
        i0, i1, dist = mutual_nn_ratio(a, b, 0.9)
        assert len(i0) == len(i1) == len(dist) == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_mutual_nn_ratio_rejects_ties_despite_rounding(dtype):
    # Find a random unit vector v whose 1 - v.v rounds below zero, then give it two identical
    # candidates: the ratio test must reject the tie as ambiguous, as it does when 1 - v.v == 0.
    gen = torch.Generator().manual_seed(4)
    for _ in range(1000):
        v = F.normalize(torch.randn(1, 32, generator=gen, dtype=dtype), dim=1)
        if float(1 - v @ v.T) < 0:
            break
    else:  # pragma: no cover
        pytest.skip("no vector with negative rounding found")
    i0, _, _ = mutual_nn_ratio(v, torch.cat([v, v]), 0.9)
    assert len(i0) == 0


def brute_force_mnn(A: torch.Tensor, B: torch.Tensor, ratio: float) -> list[tuple[int, int]]:
    D = 1 - (A @ B.T).numpy()
    out = []
    for i in range(len(A)):
        order = np.argsort(D[i])
        j = order[0]
        col = np.argsort(D[:, j])
        if col[0] != i:
            continue
        if D[i, j] < ratio * D[i, order[1]] and D[i, j] < ratio * D[col[1], j]:
            out.append((i, int(j)))
    return out


def test_mutual_nn_ratio_chunking_is_exact():
    gen = torch.Generator().manual_seed(2)
    base = F.normalize(torch.randn(260, 12, generator=gen), dim=1)
    A = base[:230]
    B = F.normalize(base[30:] + 0.25 * torch.randn(230, 12, generator=gen), dim=1)  # 200 shared
    reference = mutual_nn_ratio(A, B, 0.9, chunk=10_000)
    assert 30 < len(reference[0]) < 230  # some kept, some rejected: the test has teeth
    assert list(zip(reference[0].tolist(), reference[1].tolist())) == brute_force_mnn(A, B, 0.9)
    for chunk in (1, 3, 64, 229, 230, 231):
        i0, i1, dist = mutual_nn_ratio(A, B, 0.9, chunk=chunk)
        assert torch.equal(i0, reference[0]) and torch.equal(i1, reference[1]), chunk
        torch.testing.assert_close(dist, reference[2])


# --------------------------------------------------------------------------- dense level


def test_match_dense_level_border_and_valid_extent():
    # Maps 8 x 10 (h x w), C = 256 (random vectors are then far from each other).
    # Valid extents: A (w 8, h 6), B (w 9, h 5). Inside both, B = A cell for cell.
    # Padding holds exact copies of valid cells of the other image: if padding took part,
    # those cells would get two identical candidates and fail the ratio test.
    gen = torch.Generator().manual_seed(3)
    fa = random_map(256, 8, 10, gen)
    fb = random_map(256, 8, 10, gen)
    fb[:, :5, :8] = fa[:, :5, :8]
    fb[:, 6, 0:8] = fa[:, 2, 0:8]  # B padding (rows >= 5) copies A row 2
    fa[:, 7, 0:9] = fb[:, 3, 0:9]  # A padding (rows >= 6) copies B row 3
    fa[:, 0:5, 9] = fb[:, 0:5, 1]  # A padding (cols >= 8) copies B column 1
    c0, c1, dist = match_dense_level(fa, fb, (8, 6), (9, 5), 0.9)
    got = sorted(map(tuple, c0.tolist()))
    # Interior of both: x in [1, 8 - 2] (A's width is the tighter), y in [1, 5 - 2] (B's height).
    expected = sorted((x, y) for x in range(1, 7) for y in range(1, 4))
    assert got == expected
    assert torch.equal(c0, c1)
    assert float(dist.abs().max()) < 1e-9
    # Without the border rule the outer ring of the common region comes back as well
    # (A's row 5 and B's column 8 are unrelated random cells: nothing else matches).
    c0, c1, _ = match_dense_level(fa, fb, (8, 6), (9, 5), 0.9, drop_border=False)
    assert sorted(map(tuple, c0.tolist())) == sorted((x, y) for x in range(8) for y in range(5))
    assert torch.equal(c0, c1)
    # Whatever the extents, no returned cell lies outside them.
    c0, c1, _ = match_dense_level(fa, fb, (5, 4), (9, 5), 0.9, drop_border=False)
    assert c0[:, 0].max() < 5 and c0[:, 1].max() < 4
    assert sorted(map(tuple, c0.tolist())) == sorted((x, y) for x in range(5) for y in range(4))


# --------------------------------------------------------------------------- refinement


def test_refine_to_children_follows_known_shift():
    # Level 0: B = A shifted by (2, 4) pixels, so parent (X, Y) at level 1 in A corresponds to
    # (X + 1, Y + 2) in B and each A child (x, y) to (x + 2, y + 4), distance 0; every other
    # child of the B parent is an unrelated random vector (distance ~1).
    gen = torch.Generator().manual_seed(4)
    fa = random_map(32, 16, 16, gen)
    fb = random_map(32, 16, 16, gen)
    fb[:, 4:, 2:] = fa[:, :12, :14]
    parents0 = torch.tensor([[X, Y] for X in range(0, 7) for Y in range(0, 6)])
    parents1 = parents0 + torch.tensor([1, 2])
    # One more parent pair whose B children are four copies of the first A child: every
    # child comparison is a tie, so the ratio test rejects them all. A cell (6, 6), B cell (0, 0).
    # (An axis vector, so that 1 - cos is exactly 0: see the rounding test further down.)
    fa[:, 12, 12] = torch.eye(32, dtype=torch.float64)[0]
    fb[:, 0:2, 0:2] = fa[:, 12, 12][:, None, None]
    parents0 = torch.cat([parents0, torch.tensor([[6, 6]])])
    parents1 = torch.cat([parents1, torch.tensor([[0, 0]])])
    n_good = len(parents0) - 1

    c0, c1, dist, parent = refine_to_children(fa, fb, parents0, parents1, (16, 16), (16, 16), ChildTest(0.9))
    assert len(c0) == 2 * n_good
    assert torch.equal(c1 - c0, torch.tensor([2, 4]).expand_as(c0))
    assert torch.equal(c0 // 2, parents0[parent]) and torch.equal(c1 // 2, parents1[parent])
    assert torch.bincount(parent, minlength=len(parents0)).tolist() == [2] * n_good + [0]
    assert float(dist.abs().max()) < 1e-9
    assert len(set(map(tuple, torch.cat([c0, c1], 1).tolist()))) == len(c0)

    # All four children survive when allowed.
    c0, c1, _, parent = refine_to_children(fa, fb, parents0, parents1, (16, 16), (16, 16), ChildTest(0.9, max_per_parent=4))
    assert len(c0) == 4 * n_good and torch.equal(c1 - c0, torch.tensor([2, 4]).expand_as(c0))
    assert torch.bincount(parent, minlength=len(parents0)).tolist() == [4] * n_good + [0]

    # Children outside the valid extent of level l-1 are never returned: A's level 0 valid
    # width 13 drops x = 13 (children of parents X = 6, which keep only x = 12).
    c0, c1, _, parent = refine_to_children(fa, fb, parents0, parents1, (13, 16), (16, 16), ChildTest(0.9, max_per_parent=4))
    assert int(c0[:, 0].max()) == 12
    assert torch.equal(c1 - c0, torch.tensor([2, 4]).expand_as(c0))
    per_parent = torch.bincount(parent, minlength=len(parents0))
    assert per_parent[parents0[:, 0] == 6][:-1].tolist() == [2] * 6
    assert per_parent[parents0[:, 0] < 6].tolist() == [4] * 36

    # A duplicated parent match yields its children once.
    dup0 = torch.cat([parents0[:3], parents0[:1]])
    dup1 = torch.cat([parents1[:3], parents1[:1]])
    c0, c1, _, parent = refine_to_children(fa, fb, dup0, dup1, (16, 16), (16, 16), ChildTest(0.9))
    assert len(c0) == 6 and parent.tolist().count(3) == 0

    # No parents: empty, typed outputs.
    c0, c1, dist, parent = refine_to_children(fa, fb, parents0[:0], parents1[:0], (16, 16), (16, 16), ChildTest(0.9))
    assert c0.shape == (0, 2) and c1.shape == (0, 2) and len(dist) == 0 and len(parent) == 0


# --------------------------------------------------------------------------- cascade helpers


def test_estimate_level_fundamental_and_epipolar_inliers():
    # Rectified stereo: x1 = x0 + (disparity, 0), the true F is [(1, 0, 0)]_x.
    rng = np.random.default_rng(5)
    x0 = rng.uniform(0, 200, (40, 2))
    x1 = x0 + np.column_stack([rng.uniform(5, 40, 40), np.zeros(40)])
    x1[0, 1] += 30.0  # one outlier, least confident
    conf = np.linspace(10, 1, 40)[::-1].copy()  # outlier first in the list but lowest confidence
    F_top8 = estimate_level_fundamental(x0, x1, conf, "top8", 1.0)
    F_true = geometry.skew([1.0, 0.0, 0.0])
    np.testing.assert_allclose(F_top8 / F_top8[1, 2] * F_true[1, 2], F_true, atol=1e-9)
    cv2.setRNGSeed(0)
    F_ransac = estimate_level_fundamental(x0, x1, None, "ransac", 1.0)
    assert F_ransac is not None
    # Sampson of the outlier = 30^2 / 2 = 450 px^2 -> 21.2 px.
    keep = epipolar_inliers(F_top8, x0, x1, 21.0)
    assert keep.tolist() == [False] + [True] * 39
    assert epipolar_inliers(F_top8, x0, x1, 21.3).all()
    assert epipolar_inliers(F_ransac, x0, x1, 2.0).tolist() == [False] + [True] * 39
    assert estimate_level_fundamental(x0[:7], x1[:7], conf[:7], "top8", 1.0) is None
    with pytest.raises(ValueError, match="top8"):
        estimate_level_fundamental(x0, x1, conf, "magic", 1.0)


# --------------------------------------------------------------------------- pipeline


def pyramid(level0: torch.Tensor, n_levels: int) -> list[torch.Tensor]:
    """Level l = level 0 average-pooled with stride 2^l (then normalised by match_pyramids)."""
    return [level0] + [F.avg_pool2d(level0[None], 2**l)[0] for l in range(1, n_levels)]


def rectified_scene(seed: int = 0, nb: int = 8, sigma: float = 0.06, sigma_outlier: float = 0.12):
    """Level-0 maps of a synthetic rectified pair built from 16 x 16 blocks.

    Block (bx, by) of B copies block (bx - k, by) of A (k = 1 or 2 at random: horizontal
    disparity 16 or 32 px, two depth layers) plus a little noise. One block, B (5, 4), copies
    A (4, 3): a vertical displacement of 16 px that no rectified geometry explains (an
    outlier for the epipolar cascade); its noise is higher, so its confidence is lower.
    A blocks used twice are dropped (B gets random content there). Returns the maps and
    src: B block -> A block.
    """
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    size = 16 * nb
    fa = F.normalize(torch.randn(64, size, size, generator=gen), dim=0)
    fb = F.normalize(torch.randn(64, size, size, generator=gen), dim=0)
    src = {}
    for by in range(nb):
        for bx in range(nb):
            k = int(rng.integers(1, 3))
            if bx - k >= 0:
                src[(bx, by)] = (bx - k, by)
    outlier, outlier_src = (5, 4), (4, 3)
    src = {b: a for b, a in src.items() if a != outlier_src}
    src[outlier] = outlier_src
    uses: dict = {}
    for a in src.values():
        uses[a] = uses.get(a, 0) + 1
    src = {b: a for b, a in src.items() if uses[a] == 1}
    for (bx, by), (ax, ay) in src.items():
        block = fa[:, ay * 16 : ay * 16 + 16, ax * 16 : ax * 16 + 16]
        noise = sigma_outlier if (bx, by) == outlier else sigma
        fb[:, by * 16 : by * 16 + 16, bx * 16 : bx * 16 + 16] = F.normalize(
            block + noise * torch.randn(block.shape, generator=gen), dim=0
        )
    return fa, fb, src, outlier


def true_match(k0: np.ndarray, k1: np.ndarray, src: dict) -> np.ndarray:
    blocks = (k1 // 16).astype(int)
    ok = []
    for p0, p1, b in zip(k0, k1, blocks):
        a = src.get(tuple(b))
        ok.append(a is not None and np.array_equal(p1 - p0, 16 * (b - np.array(a))))
    return np.array(ok)


def check_output(out: dict, levels: range) -> None:
    n = len(out["keypoints0"])
    assert out["keypoints0"].shape == out["keypoints1"].shape == (n, 2)
    assert out["scores"].shape == (n,)
    assert np.all(out["scores"] > 0.5) and np.all(out["scores"] <= 1.0 + 1e-6)
    assert sorted(out["counts_before"]) == sorted(out["counts_after"]) == list(levels)
    assert out["counts_after"][0] == n
    for level in levels:
        assert out["counts_after"][level] <= out["counts_before"][level]
    # Level-0 keypoints are integer pixels (cell centres of stride 1).
    assert np.array_equal(out["keypoints0"], np.round(out["keypoints0"]))


@pytest.fixture(scope="module")
def rectified():
    fa, fb, src, outlier = rectified_scene()
    return pyramid(fa, 5), pyramid(fb, 5), src, outlier


def test_match_pyramids_direct_on_synthetic_pair(rectified):
    pa, pb, src, outlier = rectified
    out = match_pyramids(pa, pb, (128, 128), (128, 128), E3CMSettings(cascade=False))
    check_output(out, range(5))
    k0, k1 = out["keypoints0"], out["keypoints1"]
    assert len(k0) > 150
    assert true_match(k0, k1, src).all()
    # Every deep match doubles at each of the 4 refinements (2 children per parent).
    assert out["counts_after"][0] == 16 * out["counts_after"][4]
    # No cascade: no F, no rejection; the outlier block is matched (vertical offset 16).
    assert out["fundamentals"] == {} and out["rejection"] == {}
    from_outlier = np.all((k1 // 16).astype(int) == outlier, axis=1)
    assert from_outlier.sum() == 16
    assert np.all(k1[from_outlier] - k0[from_outlier] == 16)


@pytest.mark.parametrize("estimator", ["top8", "ransac"])
def test_match_pyramids_cascade_removes_off_epipolar_matches(rectified, estimator):
    pa, pb, src, outlier = rectified
    cv2.setRNGSeed(0)
    direct = match_pyramids(pa, pb, (128, 128), (128, 128), E3CMSettings(cascade=False))
    # Thresholds given explicitly (the cell sizes of levels 1..4), so the level where the
    # outlier goes is known: Sampson = 16^2 / 2 = 128 px^2 -> 11.3 px, kept by the 16 px
    # threshold of level 3 and removed by the 8 px one of level 2.
    settings = E3CMSettings(estimator=estimator, sampson_px=(2.0, 4.0, 8.0, 16.0))
    out = match_pyramids(pa, pb, (128, 128), (128, 128), settings)
    check_output(out, range(5))
    k0, k1 = out["keypoints0"], out["keypoints1"]
    assert true_match(k0, k1, src).all()
    # Exactly the 16 outlier matches are gone.
    assert len(k0) == len(direct["keypoints0"]) - 16
    assert np.all(k1[:, 1] == k0[:, 1])
    assert not np.any(np.all((k1 // 16).astype(int) == outlier, axis=1))
    assert set(out["rejection"]) == {0, 1, 2, 3}
    assert set(out["fundamentals"]) == {1, 2, 3, 4}
    assert out["rejection"][3] == "applied" and out["rejection"][2] == "applied"
    assert out["counts_before"][3] == out["counts_after"][3]  # 11.3 px < 16: nothing removed yet
    assert out["counts_before"][2] - out["counts_after"][2] == 4  # the outlier's 4 level-2 cells
    for level, reason in out["rejection"].items():
        F_above = out["fundamentals"][level + 1]
        assert (reason == "applied") == (F_above is not None)
        if reason != "applied":
            assert reason.startswith("skipped")
    if estimator == "top8":
        # The 8 most confident level-4 matches exclude the noisier outlier: F_4 is exact.
        F4 = out["fundamentals"][4]
        F_true = geometry.skew([1.0, 0.0, 0.0])
        np.testing.assert_allclose(F4 / F4[1, 2] * F_true[1, 2], F_true, atol=1e-6)

    # With the estimator's default thresholds the outlier goes too (at some level), and
    # nothing true is lost.
    cv2.setRNGSeed(0)
    out = match_pyramids(pa, pb, (128, 128), (128, 128), E3CMSettings(estimator=estimator))
    assert true_match(out["keypoints0"], out["keypoints1"], src).all()
    assert len(out["keypoints0"]) == len(direct["keypoints0"]) - 16


def test_match_pyramids_pure_translation_is_degenerate_for_top8():
    # B = A shifted by (16, 32): all matches obey one homography, so 8 points do not fix F.
    # The top-8 estimate is then None at every level and rejection is reported as skipped;
    # nothing is lost.
    gen = torch.Generator().manual_seed(6)
    fa = F.normalize(torch.randn(64, 128, 128, generator=gen), dim=0)
    fb = F.normalize(torch.randn(64, 128, 128, generator=gen), dim=0)
    fb[:, 32:, 16:] = fa[:, :96, :112]
    pa, pb = pyramid(fa, 5), pyramid(fb, 5)
    direct = match_pyramids(pa, pb, (128, 128), (128, 128), E3CMSettings(cascade=False))
    out = match_pyramids(pa, pb, (128, 128), (128, 128), E3CMSettings(estimator="top8"))
    for result in (direct, out):
        check_output(result, range(5))
        assert np.all(result["keypoints1"] - result["keypoints0"] == [16, 32])
    # Level 4 interior: A cells x 1..5 (B's x + 1 <= 6), y 1..4 (B's y + 2 <= 6) -> 20.
    assert direct["counts_after"][4] == 20 and len(direct["keypoints0"]) == 320
    assert len(out["keypoints0"]) == 320
    assert all(v is None for v in out["fundamentals"].values())
    assert all(r.startswith("skipped") for r in out["rejection"].values())


def test_match_pyramids_few_matches_skip_rejection():
    # A 16 x 16 image, 3 levels (stride 4 at the top): the valid level-2 extent is 4 x 4,
    # whose interior is 2 x 2 -> 4 matches, fewer than 8: no F at level 2, rejection at
    # level 1 skipped. Level 1 then has 4 x 2 = 8 matches: F_1 is estimated (or found
    # degenerate) and the rejection at level 0 says which.
    gen = torch.Generator().manual_seed(7)
    fa = F.normalize(torch.randn(64, 16, 16, generator=gen), dim=0)
    fb = F.normalize(fa + 0.05 * torch.randn(64, 16, 16, generator=gen), dim=0)
    out = match_pyramids(pyramid(fa, 3), pyramid(fb, 3), (16, 16), (16, 16), E3CMSettings())
    check_output(out, range(3))
    assert out["counts_after"][2] == 4
    assert out["fundamentals"][2] is None
    assert out["rejection"][1].startswith("skipped") and "fewer than 8" in out["rejection"][1]
    assert out["counts_before"][1] == out["counts_after"][1] == 8
    assert (out["rejection"][0] == "applied") == (out["fundamentals"][1] is not None)
    # B is A plus noise, so every match is the identity; nothing true was rejected.
    assert len(out["keypoints0"]) == 16
    assert np.array_equal(out["keypoints0"], out["keypoints1"])


def test_match_pyramids_drops_matches_in_padding():
    # Maps cover 128 x 128 but the images are 120 x 100: no keypoint beyond the image.
    fa, fb, src, _ = rectified_scene(seed=0)
    out = match_pyramids(pyramid(fa, 5), pyramid(fb, 5), (120, 100), (120, 100), E3CMSettings(cascade=False))
    for k in (out["keypoints0"], out["keypoints1"]):
        assert len(k) > 50
        assert k[:, 0].max() <= 119 and k[:, 1].max() <= 99
    assert true_match(out["keypoints0"], out["keypoints1"], src).all()


# --------------------------------------------------------------------------- settings


def test_settings_validation():
    s = E3CMSettings()
    assert s.cascade and s.estimator == "top8" and len(s.ratio) == 5 and len(s.sampson_px) == 4
    assert E3CMSettings(estimator="ransac").estimator == "ransac"
    # sampson_px defaults per estimator; a given value wins and is stored as floats.
    for estimator in ("top8", "ransac", "prosac"):
        assert E3CMSettings(estimator=estimator).sampson_px == tuple(DEFAULT_SAMPSON_PX[estimator])
    assert E3CMSettings(estimator="ransac", sampson_px=[3, 4, 5, 6]).sampson_px == (3.0, 4.0, 5.0, 6.0)
    with pytest.raises(ValueError, match="estimator"):
        E3CMSettings(estimator="lmeds")
    with pytest.raises(ValueError, match="ratio"):
        E3CMSettings(ratio=(0.9, 0.9, 0.9, 0.9))
    with pytest.raises(ValueError, match="sampson_px"):
        E3CMSettings(sampson_px=(1.0, 2.0, 3.0))
    d = E3CMSettings(ratio=[0.8] * 5).to_dict()
    assert d["ratio"] == [0.8] * 5 and "notes" not in d and d["estimator"] == "top8"


def pixel_major(feat):
    """The same C x H x W values stored channels-last."""
    return feat.permute(1, 2, 0).contiguous().permute(2, 0, 1)


def test_unit_pixels_gather_the_rows_of_the_normalised_map_bit_for_bit():
    gen = torch.Generator().manual_seed(3)
    for shape in ((64, 37, 53), (24, 16, 16), (64, 70, 90)):
        raw = torch.randn(*shape, generator=gen).relu_() * 5
        raw[:, 0, 0] = 0  # a zero vector: the clamp
        want = F.normalize(raw, dim=0).permute(1, 2, 0).reshape(-1, shape[0])
        index = torch.randint(0, shape[1] * shape[2], (500,), generator=gen)
        index[:2] = 0
        assert torch.equal(UnitPixels.of(raw).gather(index), want[index]), shape
        # Rows kept in bf16 (a bf16 backbone's own output) widen to the same map exactly.
        narrow = raw.bfloat16()
        rows = pixel_rows(pixel_major(narrow))
        assert rows.dtype == torch.bfloat16 and rows.is_contiguous()
        unit = UnitPixels.of(narrow.float(), rows=rows)
        assert torch.equal(unit.gather(index), F.normalize(narrow.float(), dim=0).permute(1, 2, 0).reshape(-1, shape[0])[index])
        assert torch.equal(pixel_norms(raw), raw.norm(2, 0).clamp_min(1e-12).reshape(-1))


def test_channel_norm_is_torchs_norm_bit_for_bit(monkeypatch):
    from e3cm_bench.matching import norms

    gen = torch.Generator().manual_seed(5)
    # Sizes around torch's parallel grain, and a gather's C x N x 4; a channels-last map, a
    # float64 one and a small one take torch's norm.
    for shape in ((64, 37, 153), (64, 120, 160), (16, 33, 517), (128, 7, 700), (512, 3001, 4)):
        raw = torch.randn(*shape, generator=gen).relu_() * 7
        raw[:, 1, 2] = 0
        assert norms.ordered_is_exact(raw), shape
        assert torch.equal(norms.ordered_norm(raw), raw.norm(2, 0, keepdim=True)), shape
        assert torch.equal(norms.normalize_channels(raw), F.normalize(raw, dim=0)), shape
    for other in (pixel_major(torch.randn(64, 80, 90, generator=gen)), torch.randn(64, 80, 90, dtype=torch.float64),
                  torch.randn(64, 20, 30, generator=gen)):
        assert not norms.ordered_is_exact(other)
        assert torch.equal(norms.normalize_channels(other), F.normalize(other, dim=0))

    # Where the ordered sum would not give torch's bits, the probe says so and torch's norm is used.
    monkeypatch.setattr(norms, "_checked", {})
    monkeypatch.setattr(norms, "ordered_norm", lambda feat: feat.double().norm(2, 0, keepdim=True).float() * (1 + 1e-6))
    raw = torch.randn(64, 37, 153, generator=gen).relu_()
    assert not norms.ordered_is_exact(raw)
    assert torch.equal(pixel_norms(raw), raw.norm(2, 0).clamp_min(1e-12).reshape(-1))


def test_mutual_diagonal_is_argmax_both_ways_ties_included():
    from e3cm_bench.matching.cascade import _mutual_diagonal

    gen = torch.Generator().manual_seed(11)
    for p in (1, 2, 4, 16, 64, 256):
        # Values on a coarse grid, so that rows and columns often hold equal maxima (on the
        # coarsest, most entries equal the maximum of their row), and some patches without ties.
        sim = (torch.rand(40, p, p, generator=gen) * 6).round() / 6
        sim[20:30] = (torch.rand(10, p, p, generator=gen) * 1.2).round()
        sim[:5] = torch.rand(5, p, p, generator=gen)
        index = torch.arange(p)
        want = (sim.argmax(dim=2) == index) & (sim.argmax(dim=1) == index)
        got = _mutual_diagonal(sim.clone())
        assert torch.equal(got, want), p
        if p > 1:
            assert want.any() and (~want).any()


def test_refine_gather_is_advanced_indexing_on_both_layouts():
    from e3cm_bench.matching.refine import _gather

    gen = torch.Generator().manual_seed(2)
    x = torch.randn(1, 24, 50, 70, generator=gen)
    kids = torch.stack([torch.randint(0, 70, (300, 4), generator=gen), torch.randint(0, 50, (300, 4), generator=gen)], -1)
    for feat in (x[0], x.contiguous(memory_format=torch.channels_last)[0]):
        got = _gather(feat, kids)
        assert got.is_contiguous() and torch.equal(got, feat[:, kids[..., 1], kids[..., 0]])


def test_first_of_each_is_that_of_torch_unique_over_rows():
    from e3cm_bench.matching.refine import first_of_each, row_keys

    def reference(rows):
        uniq, inverse = torch.unique(rows, dim=0, return_inverse=True)
        first = torch.full((len(uniq),), len(rows), dtype=torch.long)
        return first.scatter_reduce_(0, inverse, torch.arange(len(rows)), reduce="amin")

    gen = torch.Generator().manual_seed(11)
    cases = [torch.randint(0, 5, (300, 4), generator=gen),  # many repeats
             torch.randint(-40, 1600, (5000, 4), generator=gen),  # negative cells, level-0 ranges
             torch.randint(0, 7, (50, 2), generator=gen).repeat(3, 1),
             torch.tensor([[3, 1]]),
             torch.tensor([[0, 2**40], [2**40, 0], [0, 2**40]])]  # a span past 2^62: torch.unique itself
    for rows in cases:
        assert torch.equal(first_of_each(rows), reference(rows)), rows.shape
    assert row_keys(cases[-1]) is None and row_keys(cases[0].float()) is None
    rows = cases[1].tolist()  # the keys sort as the rows do, lexicographically
    assert torch.argsort(row_keys(cases[1]), stable=True).tolist() == sorted(range(len(rows)), key=lambda i: rows[i])
