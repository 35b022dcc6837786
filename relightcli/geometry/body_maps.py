"""Prior maps of the fitted bodies in the working crop: what the crop camera sees of them from
the front, and what a camera looking back along +Z from behind them sees (the farthest surface
along each pixel's ray), as depth and normals in the crop's world frame (compose.CROP_RECT,
orthographic along -Z, +Z toward the viewer).

Traced once per photo by Embree primary rays (render.camera.render_pixel_geometry), one per
pixel each way; the pipeline traces the person's pixels only (stage_body_maps). Later stages read them from the Frame (the ray
tracer shades the front hits; the `body_normal` / `body_depth` layers write them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relightcli.compose import CROP_RECT
from relightcli.render.camera import PixelGeometry, pixel_centres, render_pixel_geometry
from relightcli.render.scene import Scene


@dataclass
class BodyMaps:
    """The bodies seen in an (R, R) crop.

    mask (R, R) bool: a body covers the pixel. front_depth, back_depth (R, R) float32 world z
    of the nearest and the farthest body surface along the pixel's ray (front >= back), 0 off
    the mask. front_normal (R, R, 3) float32 unit shading normals facing the camera (n_z >= 0
    but for a few silhouette pixels), back_normal facing away from it; zero off the mask.
    front: the camera's hits (render.camera.PixelGeometry, scene-local positions), which the
    ray tracer shades."""

    mask: np.ndarray
    front_depth: np.ndarray
    back_depth: np.ndarray
    front_normal: np.ndarray
    back_normal: np.ndarray
    front: PixelGeometry


def bodies_scene(vertex_sets: list, triangles: np.ndarray) -> Scene | None:
    """One Embree scene of several posed bodies (each (V, 3) float, the same triangles
    (F, 3)); None for no body."""
    if not vertex_sets:
        return None
    count = len(vertex_sets[0])
    faces = np.concatenate([triangles + k * count for k in range(len(vertex_sets))])
    return Scene(np.concatenate(vertex_sets), faces, threads=1)


def render_body_maps(scene: Scene, resolution: int, where=None) -> BodyMaps:
    """Front and back depth and normals of the scene's bodies in the (R, R) crop, at the pixels
    `where` (R, R) bool (default: every pixel under the bodies' x/y bounds); zero elsewhere.
    The back rays start only where a front ray hit (a ray that misses a closed body from the
    front misses it from behind)."""
    size = (resolution, resolution)
    where = _under_bounds(scene, resolution) if where is None else where
    front = render_pixel_geometry(scene, CROP_RECT, size, where=where)
    back = render_pixel_geometry(scene, CROP_RECT, size, where=front.mask, from_behind=True)
    mask = front.mask & back.mask
    return BodyMaps(mask=mask, front_depth=_world_depth(front, scene, mask),
                    back_depth=_world_depth(back, scene, mask),
                    front_normal=front.normal * mask[..., None], back_normal=back.normal * mask[..., None],
                    front=front)


def _under_bounds(scene: Scene, resolution: int) -> np.ndarray:
    """(R, R) bool: the crop pixels whose centres lie within the scene's x/y bounds, the only
    ones a ray along z can hit."""
    lo, hi = scene.to_world(scene.bounds_local[0]), scene.to_world(scene.bounds_local[1])
    x = pixel_centres(CROP_RECT, (resolution, 1))[0, :, 0]
    y = pixel_centres(CROP_RECT, (1, resolution))[:, 0, 1]
    return ((y >= lo[1]) & (y <= hi[1]))[:, None] & ((x >= lo[0]) & (x <= hi[0]))[None, :]


def _world_depth(hits: PixelGeometry, scene: Scene, mask: np.ndarray) -> np.ndarray:
    """(R, R) float32 world z of the hits (scene-local + the scene's centre), 0 off the mask."""
    z = hits.position[..., 2].astype(np.float64) + scene.centre[2]
    return np.where(mask, z, 0.0).astype(np.float32)
