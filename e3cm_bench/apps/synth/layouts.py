"""Embedded benchmark data, written deterministically (seeded) in the real benchmarks' layouts.

- `write_hpatches`: HPatches-format sequences from matplotlib's real photograph: `v_`
  sequences warped by random homographies of growing strength, `i_` sequences with
  photometric changes of growing strength (identity H, as in HPatches). Exact H_1_k.
- `write_scene_pairs`: two-view pairs of the non-planar room scene (`scene.room_scene`:
  floor, walls, a box, a staircase) in the SuperGlue/YFCC pair-list format, with exact K
  and relative poses. Textures come from the same photograph and procedural noise.

So the ordinary `hpatches` and `yfcc` commands run on them, with nothing downloaded.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from e3cm_bench.ground.files import write_atomically
from e3cm_bench.apps.synth.scene import intrinsics, look_at, relative_pose, render, room_scene
from e3cm_bench.apps.synth.textures import procedural_scene, sample_photo

GENERATOR_VERSION = 1  # bump when the generated data changes, so cached copies are rebuilt
QUICK_VERSION = 2  # 2: the quick set holds an illumination sequence too
CROP = (384, 448)  # width, height of the HPatches-format images, cut from the 512 x 600 photo


def _write_rgb(path: Path, image: np.ndarray) -> None:
    from e3cm_bench.drawing.matches import save_image  # written atomically, never through a link at `path`

    save_image(path, image)


def random_homography(rng: np.random.Generator, size: tuple[int, int], strength: float) -> np.ndarray:
    """A viewpoint-like H about the image centre: rotation, scale and corner perspective, all
    growing with `strength` (0 = identity; 0.28, the demo's strongest, up to 17 degrees,
    28% scale and corners moved by about 7% of the image size)."""
    w, h = size
    centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    angle = np.deg2rad(rng.uniform(-60, 60) * strength)
    scale = 1 + rng.uniform(-1, 1) * strength
    similarity = np.diag([scale, scale, 1.0]) @ np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    moved = corners + rng.normal(0, strength * 0.25 * min(w, h), corners.shape).astype(np.float32)
    perspective = cv2.getPerspectiveTransform(corners, moved)
    H = perspective @ np.linalg.inv(centre) @ similarity @ centre
    return H / H[2, 2]


def photometric_change(image: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """Gamma, exposure, colour cast, blur and sensor noise, each growing with `strength` (0..1)."""
    x = image.astype(np.float32) / 255.0
    x = x ** np.exp(rng.uniform(-1, 1) * 0.8 * strength)
    x = x * (1 + rng.uniform(-0.6, 0.3) * strength) * (1 + rng.uniform(-0.25, 0.25, 3) * strength)
    sigma = 1.5 * strength
    if sigma > 0.3:
        x = cv2.GaussianBlur(x, (0, 0), sigma)
    x = x + rng.normal(0, 0.03 * strength, x.shape)
    return np.clip(x * 255 + 0.5, 0, 255).astype(np.uint8)


def write_hpatches(root: str | Path, seed: int = 0, n_viewpoint: int = 2, n_illumination: int = 1) -> Path:
    """HPatches layout under `root`: v_hopper{i}, i_hopper{i}, each 1..6.ppm with H_1_2..H_1_6."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    photo = sample_photo()
    ph, pw = photo.shape[:2]
    w, h = CROP
    for i in range(n_viewpoint):
        # Each sequence starts from its own crop of the photograph; the margin feeds the warps.
        ox, oy = int(rng.integers(0, pw - w + 1)), int(rng.integers(0, ph - h + 1))
        crop_to_photo = np.array([[1, 0, ox], [0, 1, oy], [0, 0, 1]], np.float64)
        folder = root / f"v_hopper{i + 1}"
        _write_rgb(folder / "1.ppm", photo[oy : oy + h, ox : ox + w])
        for k in range(2, 7):
            H = random_homography(rng, CROP, strength=0.07 * (k - 1))
            warped = cv2.warpPerspective(photo, H @ np.linalg.inv(crop_to_photo), CROP, flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_REFLECT)
            _write_rgb(folder / f"{k}.ppm", warped)
            np.savetxt(folder / f"H_1_{k}", H)
    for i in range(n_illumination):
        ox, oy = int(rng.integers(0, pw - w + 1)), int(rng.integers(0, ph - h + 1))
        base = photo[oy : oy + h, ox : ox + w]
        folder = root / f"i_hopper{i + 1}"
        _write_rgb(folder / "1.ppm", base)
        for k in range(2, 7):
            _write_rgb(folder / f"{k}.ppm", photometric_change(base, rng, strength=0.2 * (k - 1)))
            np.savetxt(folder / f"H_1_{k}", np.eye(3))
    return root


def texture_maker(rng: np.random.Generator):
    """make_texture(width, height, kind) for `room_scene`: 'photo' = a crop of the photograph
    with the surface's aspect, resized; 'noise' = a procedural texture of its own seed."""
    photo = sample_photo()
    ph, pw = photo.shape[:2]

    def make_texture(width: int, height: int, kind: str) -> np.ndarray:
        if kind == "photo":
            scale = min(pw / width, ph / height) * rng.uniform(0.6, 1.0)
            cw, ch = int(width * scale), int(height * scale)
            x, y = int(rng.integers(0, pw - cw + 1)), int(rng.integers(0, ph - ch + 1))
            return cv2.resize(photo[y : y + ch, x : x + cw], (width, height), interpolation=cv2.INTER_AREA)
        return procedural_scene((width, height), seed=int(rng.integers(0, 1 << 30)))

    return make_texture


SCENE_SIZE = (640, 480)
SCENE_FOCAL = 500.0


def scene_cameras(rng: np.random.Generator, strength: float) -> tuple[tuple, tuple]:
    """Two cameras looking into the room; baseline and viewing change grow with `strength` (0..1)."""
    centre0 = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.2), rng.uniform(0.0, 0.8)])
    target0 = np.array([rng.uniform(-0.8, 0.8), rng.uniform(0.2, 0.9), 6.5])
    direction = rng.normal(0, 1, 3) * np.array([1.0, 0.3, 0.5])
    baseline = (0.25 + 0.9 * strength) * direction / np.linalg.norm(direction)
    target1 = target0 + rng.normal(0, 0.6 * strength + 0.1, 3) * np.array([1.0, 0.5, 0.0])
    return look_at(centre0, target0), look_at(centre0 + baseline, target1)


def seeded_room(seed: int) -> tuple[np.random.Generator, list, np.ndarray]:
    """The random generator after building the room, the room's planes, and the camera's K."""
    rng = np.random.default_rng(seed)
    return rng, room_scene(texture_maker(rng), rng), intrinsics(*SCENE_SIZE, SCENE_FOCAL)


def write_scene_pairs(root: str | Path, seed: int = 0, n_pairs: int = 6) -> Path:
    """YFCC pair-list layout under `root`: images/room/p{k}_{a,b}.png and pairs_with_gt.txt."""
    root = Path(root)
    rng, planes, K = seeded_room(seed)
    lines = []
    for k in range(n_pairs):
        (R0, t0), (R1, t1) = scene_cameras(rng, strength=k / max(n_pairs - 1, 1))
        names = (f"room/p{k}_a.png", f"room/p{k}_b.png")
        for name, (R, t) in zip(names, ((R0, t0), (R1, t1))):
            _write_rgb(root / "images" / name, render(planes, K, R, t, SCENE_SIZE).image)
        T = relative_pose(R0, t0, R1, t1)
        numbers = [*K.ravel(), *K.ravel(), *T.ravel()]
        lines.append(" ".join([*names, "0", "0", *(repr(float(v)) for v in numbers)]))
    pairs = root / "pairs_with_gt.txt"
    write_atomically(pairs, lambda tmp: tmp.write_text("\n".join(lines) + "\n"))
    return pairs


def write_demo_data(root: str | Path, seed: int = 0, quick: bool = False) -> dict[str, Path]:
    """Both sets under `root`, reused when already written with the same seed and size.

    quick: 1 viewpoint + 1 illumination sequence (10 pairs) and 2 scene pairs (the quick demo,
    tests); else 2 viewpoint + 1 illumination sequences (15 pairs) and 6 scene pairs.
    """
    root = Path(root)
    # The quick set's version is its own: bumping it rebuilds quick data only, so that the full
    # demo's data (and the committed results made from it) stay as they are.
    stamp = {"generator": GENERATOR_VERSION, "seed": seed, "quick": quick}
    if quick:
        stamp["quick_version"] = QUICK_VERSION
    stamp_file = root / "generated.json"
    paths = {"hpatches": root / "hpatches", "scenes": root / "scenes"}
    if stamp_file.is_file() and json.loads(stamp_file.read_text()) == stamp:
        return paths
    write_hpatches(paths["hpatches"], seed, n_viewpoint=1 if quick else 2, n_illumination=1)
    write_scene_pairs(paths["scenes"], seed + 1, n_pairs=2 if quick else 6)
    write_atomically(stamp_file, lambda tmp: tmp.write_text(json.dumps(stamp)))
    return paths
