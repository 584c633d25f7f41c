"""Per-patch 3D targets from rendered depth: the world xyz each vision token of a pixels policy sees.

Spatial Forcing aligns every visual token with its own dense 3D feature from a frozen 3D model
(VGGT). Our analogue of that feature is geometric and exact: the world-frame point seen by the
token's image patch, back-projected from MuJoCo's depth render through the camera's pinhole model
(`fovy`, `cam_xpos`, `cam_xmat`), then reduced to one point per patch. The `spatial_depth` auxiliary
objective (aux_objectives.py) embeds it with a fixed random Fourier map.

Conventions (MuJoCo's, which are OpenGL's): the camera looks along its −z axis with +x to the right
of the image and +y up; `fovy` is the full vertical field of view in degrees; depth is the distance
along the optical axis in metres (not along the ray); pixel (r, c) of an image with row 0 at the top
has its centre at (c + ½, r + ½). A `PinholeCamera` describes the image as the policy sees it
(envs.FastRenderer turns some cameras' images by 180°; it turns the camera's x and y axes with them).

Patches are the policy's token grid: a `grid` × `grid` split of the image into equal squares, in
row-major order (the order of `VisionEncoder`'s flattened conv grid). A patch's point is the
coordinate-wise median over its pixels that see geometry; pixels that see none (the image's sky box;
the far clipping plane in the depth render) are left out, and a patch with no such pixel is NaN (the
objective skips it).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

BACKGROUND_FRACTION = 0.99  # depth at or beyond this fraction of the far plane: no geometry there


@dataclass(frozen=True)
class PinholeCamera:
    """A square image's pinhole camera in world coordinates.

    `rotation` columns are the world directions of the image's right, the image's up and the camera's
    back (the optical axis points along −column 2), i.e. MuJoCo's `cam_xmat` as a 3×3 matrix for an
    image shown as rendered.
    """

    position: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3)
    fovy: float  # degrees, full vertical field of view
    size: int  # image side in pixels

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return self.size / 2 / math.tan(math.radians(self.fovy) / 2)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """float64 (S, S, 3) world point of every pixel, from depth (S, S) in metres along the axis."""
        depth = np.asarray(depth, dtype=np.float64)
        if depth.shape != (self.size, self.size):
            raise ValueError(f"depth must be ({self.size}, {self.size}), got {depth.shape}")
        rays = _rays(self.size, self.focal)  # camera frame, z = -1
        points_cam = rays * depth[..., None]
        return points_cam @ np.asarray(self.rotation, dtype=np.float64).T + np.asarray(self.position)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) float pixel coordinates of world points (..., 3), and their depths."""
        rel = np.asarray(points, dtype=np.float64) - self.position
        cam = rel @ np.asarray(self.rotation, dtype=np.float64)  # R^T (p - t), row-vector form
        depth = -cam[..., 2]
        half = self.size / 2
        cols = half + self.focal * cam[..., 0] / depth - 0.5
        rows = half - self.focal * cam[..., 1] / depth - 0.5
        return np.stack([rows, cols], axis=-1), depth


@functools.cache
def _rays(size: int, focal: float) -> np.ndarray:
    centres = np.arange(size, dtype=np.float64) + 0.5 - size / 2
    x = np.broadcast_to(centres[None, :] / focal, (size, size))
    y = np.broadcast_to(-centres[:, None] / focal, (size, size))
    rays = np.stack([x, y, -np.ones((size, size))], axis=-1)
    rays.flags.writeable = False
    return rays


def patch_medians(points: np.ndarray, valid: np.ndarray, grid: int) -> np.ndarray:
    """float32 (grid², 3): per patch (row-major), the coordinate-wise median of its valid points.

    points (S, S, 3), valid (S, S) bool; S must be a multiple of `grid`. NaN where a patch has no
    valid point.
    """
    size = points.shape[0]
    if points.shape != (size, size, 3) or valid.shape != (size, size):
        raise ValueError(f"points must be (S, S, 3) and valid (S, S), got {points.shape} and {valid.shape}")
    if grid < 1 or size % grid:
        raise ValueError(f"patch grid {grid} does not divide the image side {size}")
    p = size // grid
    cells = grid * grid
    patches = points.reshape(grid, p, grid, p, 3).transpose(0, 2, 1, 3, 4).reshape(cells, p * p, 3)
    ok = valid.reshape(grid, p, grid, p).transpose(0, 2, 1, 3).reshape(cells, p * p)
    # np.nanmedian's semantics at a fraction of its cost: invalid points sort last, the median is the
    # middle one (or the mean of the middle two) of the first n = valid count.
    ordered = np.sort(np.where(ok[..., None], patches, np.inf), axis=1)
    n = ok.sum(axis=1)
    lo = np.maximum((n - 1) // 2, 0)[:, None, None]
    hi = (n // 2)[:, None, None]
    median = (np.take_along_axis(ordered, lo, 1) + np.take_along_axis(ordered, hi, 1))[:, 0] / 2
    median[n == 0] = np.nan
    return median.astype(np.float32)


def patch_xyz(depth: np.ndarray, camera: PinholeCamera, grid: int, far: float) -> np.ndarray:
    """float32 (grid², 3): the world point each image patch sees (see the module docstring).

    depth (S, S) metres, as `camera` sees the image; `far` is the far clipping plane in metres (MuJoCo:
    `model.vis.map.zfar * model.stat.extent`), where the depth of pixels without geometry lies.
    """
    valid = np.asarray(depth) < BACKGROUND_FRACTION * far
    return patch_medians(camera.backproject(depth), valid, grid)
