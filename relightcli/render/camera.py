"""Orthographic, pixel-aligned camera (DESIGN.md): looks along -Z, +Y up, row 0 at the top.

Pixel (i, j) of an H x W image over the world rectangle [x0, x1] x [y0, y1] has its centre at
x = x0 + (j + 0.5)(x1 - x0)/W, y = y1 - (i + 0.5)(y1 - y0)/H.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from relightcli.errors import UsageError
from relightcli.render.scene import Scene, orient_normals


@dataclass
class PixelGeometry:
    """What the camera sees, per pixel of an (H, W) image, in the scene's local frame.

    mask (H, W) bool: a surface is hit. position (H, W, 3) float32 local hit point;
    normal (H, W, 3) float32 unit shading normal (interpolated vertex normal, replaced by the
    geometric normal where it faces away from it); geometric_normal (H, W, 3) float32 unit,
    flipped toward the camera side of the surface. Zero outside the mask. rect: the world
    rectangle (x0, x1, y0, y1) the image covers.
    """

    mask: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    geometric_normal: np.ndarray
    rect: tuple

    @property
    def resolution(self):
        return self.mask.shape

    def with_shading_normals(self, normals, where) -> "PixelGeometry":
        """The same hits shaded with other normals (H, W, 3) (normalised here) at the pixels
        `where` (H, W) bool that hit and whose new normal lies on the geometric normal's side;
        the mesh's shading normals elsewhere. Positions and geometric normals (ray origins,
        the horizon) stay the mesh's."""
        n = np.asarray(normals, dtype=np.float32)
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        n = n / np.where(length > 0, length, 1.0)
        use = where & self.mask & (length[..., 0] > 0) & (np.sum(n * self.geometric_normal, axis=-1) > 0)
        return replace(self, normal=np.where(use[..., None], n, self.normal).astype(np.float32))

    def subsampled(self, step: int) -> "PixelGeometry":
        """Every step-th pixel's hit in both directions, starting at pixel (0, 0): pixel (i, j)
        of the result is pixel (step i, step j) of this image, and the result's rectangle puts
        its pixel centres where theirs are."""
        if step == 1:
            return self
        x0, x1, y0, y1 = self.rect
        height, width = self.mask.shape
        rows, cols = -(-height // step), -(-width // step)
        dx, dy = (x1 - x0) / width, (y1 - y0) / height
        left, top = x0 - 0.5 * dx * (step - 1), y1 + 0.5 * dy * (step - 1)
        every = np.s_[::step, ::step]
        return PixelGeometry(mask=self.mask[every], position=self.position[every],
                             normal=self.normal[every], geometric_normal=self.geometric_normal[every],
                             rect=(left, left + cols * step * dx, top - rows * step * dy, top))


def pixel_centres(rect, resolution):
    """World (x, y) of the pixel centres. rect (x0, x1, y0, y1), resolution (W, H).

    Returns (H, W, 2) float64.
    """
    x0, x1, y0, y1 = (float(c) for c in rect)
    width, height = (int(r) for r in resolution)
    if width < 1 or height < 1:
        raise UsageError(f"resolution must be positive, got {width}x{height}")
    if not (x1 > x0 and y1 > y0):
        raise UsageError(f"rectangle must have x1 > x0 and y1 > y0, got ({x0:g}, {x1:g}, {y0:g}, {y1:g})")
    x = x0 + (np.arange(width) + 0.5) * (x1 - x0) / width
    y = y1 - (np.arange(height) + 0.5) * (y1 - y0) / height
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx, yy], axis=-1)


def default_rect(scene: Scene, pad: float = 0.05):
    """The mesh's world x/y bounds padded by `pad` of their size on each side: (x0, x1, y0, y1)."""
    lo, hi = scene.to_world(scene.bounds_local[0]), scene.to_world(scene.bounds_local[1])
    dx, dy = (hi[0] - lo[0]) * pad, (hi[1] - lo[1]) * pad
    return (lo[0] - dx, hi[0] + dx, lo[1] - dy, hi[1] + dy)


def render_pixel_geometry(scene: Scene, rect, resolution, where=None, *,
                          from_behind: bool = False) -> PixelGeometry:
    """Trace one orthographic primary ray per pixel (a single batch) along -Z; with `where`
    (H, W) bool, only at those pixels (the others see nothing: no work for pixels whose
    shading nobody uses). `from_behind`: the rays start behind the scene and run along +Z, so
    each pixel sees the farthest surface from the camera (a back view in the same pixel grid;
    normals face -Z, toward those rays)."""
    centres = pixel_centres(rect, resolution)
    height, width = centres.shape[:2]
    traced = np.ones((height, width), bool) if where is None else np.asarray(where, bool)
    if traced.shape != (height, width):
        raise UsageError(f"where is {traced.shape}, the image {height}x{width}")
    # Start above the mesh's local z range, in the local frame (float64 until the cast)
    side = -1.0 if from_behind else 1.0
    z_start = scene.bounds_local[0 if from_behind else 1, 2] + side * 0.01 * scene.diagonal
    world_xy = centres[traced]
    origins = np.empty((world_xy.shape[0], 3))
    origins[:, :2] = world_xy - scene.centre[:2]
    origins[:, 2] = z_start
    directions = np.tile(np.array([0.0, 0.0, -side]), (origins.shape[0], 1))
    hits = scene.intersect(origins, directions)
    ns, ng = orient_normals(hits.geometric_normal, scene.shading_normals(hits), directions)
    position = origins + hits.t[:, None].astype(np.float64) * directions
    hit = hits.hit[:, None]
    mask = np.zeros((height, width), bool)
    mask[traced] = hits.hit

    def image(values):
        out = np.zeros((height, width, 3), np.float32)
        out[traced] = np.where(hit, values, 0.0)
        return out

    return PixelGeometry(mask=mask, position=image(position), normal=image(ns),
                         geometric_normal=image(ng), rect=tuple(float(c) for c in rect))

