"""A non-planar scene of textured rectangles, rendered by ray casting with exact geometry.

Arrays in, arrays out: no files. A scene is a list of `Plane`s (rectangles in 3D with a
texture); `render` casts one ray per pixel through a pinhole camera (K, world-to-camera R,
t), keeps the nearest hit (occlusion by depth) and samples the texture bilinearly. The
depth and the surface coordinates of every pixel come back with the image, so tests can
check that a pixel reprojected through depth and pose lands on the same surface point.

Conventions: camera x right, y down, z forward (OpenCV); pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Plane:
    """The rectangle origin + a * u + b * v, a, b in [0, 1]; texture pixel (a (W-1), b (H-1))."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: np.ndarray  # H x W x 3 uint8 RGB

    def __post_init__(self) -> None:
        self.origin, self.u, self.v = (np.asarray(x, np.float64) for x in (self.origin, self.u, self.v))
        if abs(self.u @ self.v) > 1e-9 * np.linalg.norm(self.u) * np.linalg.norm(self.v):
            raise ValueError("a plane's u and v must be orthogonal")


@dataclass
class Rendering:
    image: np.ndarray  # H x W x 3 uint8 RGB
    depth: np.ndarray  # H x W float64, z in the camera frame; inf where no surface
    plane: np.ndarray  # H x W int, index of the visible plane, -1 for none
    ab: np.ndarray  # H x W x 2 float64, the visible plane's (a, b)


def intrinsics(width: int, height: int, focal: float) -> np.ndarray:
    return np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], np.float64)


def look_at(
    centre: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, -1.0, 0.0])
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at `centre` looking at `target` (y down in the image)."""
    centre, target = np.asarray(centre, np.float64), np.asarray(target, np.float64)
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, np.float64), z)  # image x to the right of the viewing direction
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


def relative_pose(R0: np.ndarray, t0: np.ndarray, R1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """T_0to1 (4 x 4): camera-0 coordinates -> camera-1 coordinates."""
    T = np.eye(4)
    T[:3, :3] = R1 @ R0.T
    T[:3, 3] = t1 - R1 @ R0.T @ t0
    return T


def render(planes: list[Plane], K: np.ndarray, R: np.ndarray, t: np.ndarray, size: tuple[int, int],
           background: tuple[int, int, int] = (90, 90, 90)) -> Rendering:
    """Ray-cast the planes into a width x height image."""
    width, height = size
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3)
    rays_cam = pixels @ np.linalg.inv(K).T  # z = 1: the ray parameter is the depth
    rays = rays_cam @ R  # world directions (R^T d for each row)
    centre = -R.T @ t
    n_pix = len(pixels)
    depth = np.full(n_pix, np.inf)
    index = np.full(n_pix, -1)
    ab = np.zeros((n_pix, 2))
    for k, plane in enumerate(planes):
        normal = np.cross(plane.u, plane.v)
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((plane.origin - centre) @ normal) / denom
        hit = centre + s[:, None] * rays - plane.origin
        a = hit @ plane.u / (plane.u @ plane.u)
        b = hit @ plane.v / (plane.v @ plane.v)
        nearer = np.isfinite(s) & (s > 1e-6) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1) & (s < depth)
        depth[nearer], index[nearer] = s[nearer], k
        ab[nearer] = np.stack([a[nearer], b[nearer]], 1)

    image = np.empty((n_pix, 3), np.uint8)
    image[:] = background
    for k, plane in enumerate(planes):
        mine = index == k
        if not mine.any():
            continue
        th, tw = plane.texture.shape[:2]
        n = int(mine.sum())
        # cv2.remap takes maps of fewer than 32767 rows: lay the pixels out 1024 to a row.
        rows = -(-n // 1024)
        maps = np.zeros((2, rows * 1024), np.float32)
        maps[0, :n], maps[1, :n] = ab[mine, 0] * (tw - 1), ab[mine, 1] * (th - 1)
        map_x, map_y = maps.reshape(2, rows, 1024)
        sampled = cv2.remap(plane.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        image[mine] = sampled.reshape(-1, 3)[:n]
    shape = (height, width)
    return Rendering(image.reshape(*shape, 3), depth.reshape(shape), index.reshape(shape), ab.reshape(*shape, 2))


# Texture resolution on every surface: pixels per metre. At the demo's 500 px focal length a
# surface 4 m away shows 125 image pixels per metre, so texture detail is about one pixel.
PIXELS_PER_METRE = 120


def room_scene(make_texture, rng: np.random.Generator) -> list[Plane]:
    """A room seen from near the origin looking along +z: floor, back and side walls, a box on
    the floor, and a staircase. Units are metres; the floor is at y = 1.5 (1.5 m below the
    camera, y down). make_texture(width_px, height_px, kind) gives each surface its own
    texture at PIXELS_PER_METRE, kind 'photo' or 'noise', so nothing is stretched or tiled."""

    def plane(origin, u, v, kind: str = "noise") -> Plane:
        width = max(8, int(round(np.linalg.norm(u) * PIXELS_PER_METRE)))
        height = max(8, int(round(np.linalg.norm(v) * PIXELS_PER_METRE)))
        return Plane(origin, u, v, make_texture(width, height, kind))

    floor_y, back_z = 1.5, 9.0
    planes = [
        plane([-4.0, floor_y, 1.0], [8.0, 0, 0], [0, 0, back_z - 1.0]),  # floor
        plane([-4.0, -2.5, back_z], [8.0, 0, 0], [0, 4.0, 0], "photo"),  # back wall
        plane([-4.0, -2.5, 1.0], [0, 0, back_z - 1.0], [0, 4.0, 0]),  # left wall
        plane([4.0, -2.5, back_z], [0, 0, -(back_z - 1.0)], [0, 4.0, 0]),  # right wall
    ]
    # A box on the floor, left of centre, slightly turned: its front, top and right faces show.
    side = 1.3
    angle = rng.uniform(-0.35, -0.15)
    ex = np.array([np.cos(angle), 0, np.sin(angle)]) * side  # along the box's width
    ez = np.array([-np.sin(angle), 0, np.cos(angle)]) * side  # along its depth
    ey = np.array([0, -side, 0])  # up
    corner = np.array([-2.2 + rng.uniform(-0.2, 0.2), floor_y, 4.8 + rng.uniform(-0.3, 0.3)])
    planes += [
        plane(corner + ey, ex, -ey, "photo"),  # front face (top-left corner first)
        plane(corner + ey, ex, ez),  # top face
        plane(corner + ex + ey, ez, -ey, "photo"),  # right face
    ]
    # A staircase on the right rising away from the camera: risers, treads and their sides.
    x0, x1, z0, rise, run = 0.6, 3.2, 5.0 + rng.uniform(-0.3, 0.3), 0.35, 0.6
    for step in range(4):
        top = floor_y - (step + 1) * rise
        z = z0 + step * run
        depth = run if step < 3 else back_z - z  # the last step reaches the back wall
        planes.append(plane([x0, top, z], [x1 - x0, 0, 0], [0, rise, 0]))  # riser
        planes.append(plane([x0, top, z], [x1 - x0, 0, 0], [0, 0, depth]))  # tread
        planes.append(plane([x0, top, z], [0, 0, depth], [0, floor_y - top, 0]))  # left side
    return planes
