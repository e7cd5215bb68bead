"""The robust estimators of the evaluation, as backends behind one loader: ``load_estimator(name)``
gives the backend (OpenCV, the default, as SuperGlue's and LoFTR's evaluations; PoseLib,
glue-factory's MegaDepth-1500 default; or pycolmap's LO-RANSAC, COLMAP's own), each with the same three estimates
(homography, relative
pose, fundamental matrix). Which one is an evaluation setting (EvalSettings.estimator): --eval-only
may change it. A new backend is one class here and one entry in ``BACKENDS``.

Seeds: PoseLib takes its seed. OpenCV's RANSAC ignores cv2.setRNGSeed and draws its samples
from a fixed sequence of indices, so there a seed acts through the order of the
correspondences (`seeded_order`): seed 0 keeps the matcher's order (every committed number
was made so), seed s > 0 shuffles them with numpy's default_rng(s). Either way, repeats with
other seeds (--repeats) see other samples, as reruns of a randomised RANSAC would."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from e3cm_bench.geometry import two_view as geometry

OPENCV_METHODS = ("ransac", "magsac")  # F and H (geometry.two_view._F_METHODS, _H_METHODS)
# The relative pose's: RANSAC, USAC_MAGSAC (MAGSAC++) or USAC_ACCURATE (GC-RANSAC with LO)
POSE_METHODS = ("ransac", "magsac", "accurate")


def seeded_order(n: int, seed: int) -> np.ndarray | None:
    """The order OpenCV's RANSAC sees n correspondences in for this seed; None = as given."""
    return None if int(seed) == 0 else np.random.default_rng(int(seed)).permutation(n)


class OpenCVEstimator:
    """cv2's RANSAC (or USAC MAGSAC++ with method="magsac"), seeded through the points' order."""

    name = "opencv"

    def relative_pose(self, kpts0, kpts1, K0, K1, ransac: PoseRansac, sizes: tuple | None = None):
        """Essential-matrix RANSAC (or ransac.method, POSE_METHODS) on normalised points, the
        threshold divided by the mean focal (geometry.py); sizes are PoseLib's only."""
        order = seeded_order(len(kpts0), ransac.seed)
        given = (ransac.threshold_px, ransac.confidence, ransac.method)
        if order is None:
            return geometry.estimate_relative_pose(kpts0, kpts1, K0, K1, *given)
        found = geometry.estimate_relative_pose(kpts0[order], kpts1[order], K0, K1, *given)
        if found is None:
            return None
        return found[0], found[1], geometry.unshuffle(found[2], order)

    def homography(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                   method: str = "ransac"):
        order = seeded_order(len(x0), seed)
        if order is not None:
            x0, x1 = x0[order], x1[order]
        return geometry.estimate_homography(x0, x1, threshold_px, max_iters, confidence, method)

    def fundamental(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                    method: str = "ransac"):
        order = seeded_order(len(x0), seed)
        if order is not None:
            x0, x1 = x0[order], x1[order]
        return geometry.estimate_fundamental(x0, x1, method, threshold_px, confidence, max_iters)


class PoseLibEstimator:
    """PoseLib's LO-RANSAC with bundle refinement, seeded with the seed; it has one robust
    method of its own (OpenCV's `method` is not read)."""

    name = "poselib"

    def __init__(self) -> None:
        try:
            import poselib
        except ImportError:
            raise ValueError("--pose-estimator poselib needs PoseLib: pip install 'e3cm-bench[poselib]'") from None
        self.poselib = poselib

    def relative_pose(self, kpts0, kpts1, K0, K1, ransac: PoseRansac, sizes: tuple | None = None):
        """ransac.threshold_px is PoseLib's max_epipolar_error (pixels)."""
        if len(kpts0) < 5:
            return None
        size0, size1 = sizes if sizes is not None else (None, None)
        pose, info = self.poselib.estimate_relative_pose(
            np.ascontiguousarray(kpts0, np.float64), np.ascontiguousarray(kpts1, np.float64),
            _camera(K0, size0), _camera(K1, size1),
            {"max_epipolar_error": float(ransac.threshold_px), "success_prob": float(ransac.confidence),
             "seed": int(ransac.seed)}, {})
        if not info.get("num_inliers"):
            return None
        return np.asarray(pose.R), np.asarray(pose.t).ravel(), np.asarray(info["inliers"], bool)

    def homography(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                   method: str = "ransac"):
        if len(x0) < 4:
            return None
        H, info = self.poselib.estimate_homography(
            np.ascontiguousarray(x0, np.float64), np.ascontiguousarray(x1, np.float64),
            {"max_reproj_error": float(threshold_px), "max_iterations": int(max_iters),
             "success_prob": float(confidence), "seed": int(seed)}, {})
        H = np.asarray(H, dtype=np.float64)
        if not info.get("num_inliers") or not np.all(np.isfinite(H)):
            return None
        return H

    def fundamental(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                    method: str = "ransac"):
        if len(x0) < 7:
            return None
        F, info = self.poselib.estimate_fundamental(
            np.ascontiguousarray(x0, np.float64), np.ascontiguousarray(x1, np.float64),
            {"max_epipolar_error": float(threshold_px), "max_iterations": int(max_iters),
             "success_prob": float(confidence), "seed": int(seed)}, {})
        F = np.asarray(F, dtype=np.float64)
        if not info.get("num_inliers") or F.shape != (3, 3) or not np.all(np.isfinite(F)):
            return None
        return F


class PycolmapEstimator:
    """pycolmap's LO-RANSAC (COLMAP's estimators), seeded with the seed: the relative pose by
    estimate_relative_pose (tangent Sampson error, threshold in pixels), H and F by their
    estimate_*_matrix; it has one robust method of its own."""

    name = "pycolmap"

    def __init__(self) -> None:
        from e3cm_bench.ground.pycolmap import pycolmap_module

        self.pycolmap = pycolmap_module()

    def _options(self, threshold_px: float, confidence: float, seed: int, max_iters: int | None = None):
        options = self.pycolmap.RANSACOptions()
        options.max_error, options.confidence, options.random_seed = float(threshold_px), float(confidence), int(seed)
        if max_iters is not None:
            options.max_num_trials = int(max_iters)
        return options

    def _camera(self, K: np.ndarray, size: tuple[int, int] | None):
        found = _camera(K, size)
        return self.pycolmap.Camera(model="PINHOLE", width=found["width"], height=found["height"],
                                    params=found["params"])

    def relative_pose(self, kpts0, kpts1, K0, K1, ransac: PoseRansac, sizes: tuple | None = None):
        if len(kpts0) < 5:
            return None
        size0, size1 = sizes if sizes is not None else (None, None)
        found = self.pycolmap.estimate_relative_pose(
            self._camera(K0, size0), np.ascontiguousarray(kpts0, np.float64), self._camera(K1, size1),
            np.ascontiguousarray(kpts1, np.float64), self._options(ransac.threshold_px, ransac.confidence, ransac.seed))
        if found is None:
            return None
        pose = found["cam2_from_cam1"]
        return (np.asarray(pose.rotation.matrix(), np.float64), np.asarray(pose.translation, np.float64).ravel(),
                np.asarray(found["inlier_mask"], bool))

    def _matrix(self, estimate: str, key: str, least: int, x0, x1, options):
        """pycolmap's `estimate` of a 3x3 matrix (`key` of its answer) on pixel correspondences with
        RANSACOptions `options`, or None (fewer than `least` of them, or no estimate)."""
        if len(x0) < least:
            return None
        found = getattr(self.pycolmap, estimate)(
            np.ascontiguousarray(x0, np.float64), np.ascontiguousarray(x1, np.float64), options
        )
        return None if found is None else np.asarray(found[key], np.float64)

    def homography(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                   method: str = "ransac"):
        return self._matrix("estimate_homography_matrix", "H", 4, x0, x1,
                            self._options(threshold_px, confidence, seed, max_iters))

    def fundamental(self, x0, x1, threshold_px: float, max_iters: int, confidence: float, seed: int = 0,
                    method: str = "ransac"):
        return self._matrix("estimate_fundamental_matrix", "F", 7, x0, x1,
                            self._options(threshold_px, confidence, seed, max_iters))


def _camera(K: np.ndarray, size: tuple[int, int] | None) -> dict:
    K = np.asarray(K, dtype=np.float64)
    w, h = size if size is not None else (int(round(2 * K[0, 2])), int(round(2 * K[1, 2])))
    return {"model": "PINHOLE", "width": int(w), "height": int(h), "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}


BACKENDS = {backend.name: backend for backend in (OpenCVEstimator, PoseLibEstimator, PycolmapEstimator)}
ESTIMATORS = tuple(BACKENDS)
_loaded: dict[str, object] = {}


def load_estimator(name: str):
    """The backend called `name`, made once (PoseLib's import is checked here, so that a run
    without it stops before it matches anything)."""
    if name not in BACKENDS:
        raise ValueError(f"unknown estimator {name!r}; choose one of {', '.join(ESTIMATORS)}")
    if name not in _loaded:
        _loaded[name] = BACKENDS[name]()
    return _loaded[name]


def check_estimator(name: str) -> str:
    load_estimator(name)
    return name


@dataclass(frozen=True)
class PoseRansac:
    """How a relative pose is estimated: the threshold (pixels), the confidence, the backend
    (opencv or poselib) and its seed; one object, as EvalSettings gives them together."""

    threshold_px: float
    confidence: float
    estimator: str = "opencv"
    seed: int = 0
    method: str = "ransac"  # OpenCV's (POSE_METHODS); the other backends have one of their own


def relative_pose(
    kpts0: np.ndarray, kpts1: np.ndarray, K0: np.ndarray, K1: np.ndarray, ransac: PoseRansac,
    sizes: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(R, t, inlier mask) of camera 1 relative to camera 0, or None, from the backend
    `ransac.estimator`; sizes: the images' (w, h), for PoseLib's cameras."""
    return load_estimator(ransac.estimator).relative_pose(kpts0, kpts1, K0, K1, ransac, sizes)


def homography(
    x0: np.ndarray, x1: np.ndarray, threshold_px: float, max_iters: int, confidence: float,
    estimator: str = "opencv", seed: int = 0, method: str = "ransac",
) -> np.ndarray | None:
    """H mapping image-0 pixels to image-1 pixels, or None. method: OpenCV's robust method,
    ransac or magsac (MAGSAC++); PoseLib has one of its own."""
    return load_estimator(estimator).homography(x0, x1, threshold_px, max_iters, confidence, seed, method)


def fundamental(
    x0: np.ndarray, x1: np.ndarray, threshold_px: float, max_iters: int, confidence: float,
    estimator: str = "opencv", seed: int = 0, method: str = "ransac",
) -> np.ndarray | None:
    """F with x1^T F x0 = 0 (pixels), or None. opencv: cv2.findFundamentalMat with `method`
    (ransac, or magsac: USAC MAGSAC++, wxbs-benchmark's estimator), the threshold in pixels;
    poselib: its LO-RANSAC with threshold_px as max_epipolar_error."""
    if method not in OPENCV_METHODS:
        raise ValueError(f"unknown OpenCV method {method!r}; choose one of {', '.join(OPENCV_METHODS)}")
    return load_estimator(estimator).fundamental(x0, x1, threshold_px, max_iters, confidence, seed, method)


def homography_geometry(x0: np.ndarray, x1: np.ndarray, threshold_px: float, max_iters: int, confidence: float,
                        estimator: str = "opencv", seed: int = 0, method: str = "ransac") -> dict | None:
    """{"H", "inliers"}: the estimate and the matches within threshold_px of it (what COLMAP's
    two-view geometry stores); None where it fails."""
    H = homography(x0, x1, threshold_px, max_iters, confidence, estimator, seed, method)
    if H is None:
        return None
    with np.errstate(invalid="ignore"):
        error = np.linalg.norm(geometry.warp_points(H, x0) - x1, axis=1)
    return {"H": H, "inliers": np.nan_to_num(error, nan=np.inf) <= threshold_px}


def pose_geometry(
    x0: np.ndarray, x1: np.ndarray, K0, K1, ransac: PoseRansac, sizes: tuple | None = None
) -> dict | None:
    """{"R", "t", "inliers"}: the relative pose and its RANSAC's inliers; None where it fails."""
    found = relative_pose(x0, x1, K0, K1, ransac, sizes)
    if found is None:
        return None
    R, t, inliers = found
    return {
        "R": np.asarray(R, np.float64),
        "t": np.asarray(t, np.float64).ravel(),
        "inliers": np.asarray(inliers, bool),
    }
