"""Normals from the person's outline: what the silhouette alone says about the surface.

Where the outline of a smooth body is an occluding contour, the surface turns away from the
camera: its normal is perpendicular to the view (z = 0) and points out of the silhouette, along
the outline's 2D normal. Inside, a limb or a torso seen across is roughly round, so a point d
pixels in from the outline of a part R pixels in half-width has a normal whose in-plane part
points out and has length 1 - d / R (a circle's cross-section), the rest toward the viewer.

`silhouette_normals` is that shape for any mask (R: the largest distance to the outline within
a neighbourhood, the half-width of the part a pixel lies in); `blend_silhouette_normals` pulls
a net's normals toward it near the outline, where nets are least sure and the outline is most
informative, with a weight exp(-d / reach) that leaves the interior to the net.

Measured on the 20 validation scenes at 512 (true mask, the geometry prior net's normals 18.7
degrees from the truth, 24.9 within 2 px of the outline, where the truth faces the camera with
z 0.33 on average and the net with 0.52): the silhouette's normals alone are 19.4 degrees off,
the blend 16.3 (12.5 within 2 px of the outline).

Conventions (DESIGN.md): camera frame, +X right, +Y up (row 0 at the top), +Z toward the viewer.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from relightcli.compose import bounding_box

# At a 512-pixel crop: the half-width of a part is looked for within 16 px of a pixel (wider
# parts get rounded sides of that radius), the blend's weight falls by e every 16 px in from
# the outline, the distance map is smoothed by 1.5 px before its gradient gives the outline's
# direction; all scale with the crop's side. Chosen on three validation sets (true mask; relit
# / shading dB, normals' degrees): 150 scenes at 256 (T-posed and fighting figures), 20 at 512
# (T-posed) and 120 at 256 in the training split's poses (standing, resting, fighting, flying,
# sitting: the validation poses hold no one standing with the arms down, the test's):
#   without     17.68 / 19.38, 23.2   17.79 / 20.64, 18.7   16.94 / 17.81, 27.1
#   reach 8 px  -                     17.93 / 21.34, 16.1   17.05 / 17.98, 25.6
#   reach 16 px 17.92 / 19.96, 20.3   17.97 / 21.47, 16.3   17.09 / 18.03, 25.5
#   reach 24 px 17.94 / 20.02, 20.3   17.97 / 21.50, 16.6   17.11 / 18.04, 25.6
# Shading gains on with the reach while the normals turn: 16 px is best or within 0.2 degrees
# of it on all three. A radius of 8 / 24 / 32 px lost at 512.
PART_RADIUS = 16 / 512
REACH = 16 / 512
GRADIENT_SIGMA = 1.5 / 512


def silhouette_normals(inside: np.ndarray, outside_photo: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) float32 unit normals of the rounded shape the mask `inside` (H, W) bool
    outlines (zero outside it), in the camera frame.

    outside_photo: (H, W) bool pixels of the crop beyond the photo's edge, or None. The person
    may go on there, so the mask's edge along them is not an outline: they count as inside
    when distances are measured.
    """
    inside = np.asarray(inside, bool)
    normals = np.zeros(inside.shape + (3,), np.float32)
    normals[inside, 2] = 1.0  # where no outline is in the crop nothing is known: facing the camera
    return _over_outlined_box(normals, inside, outside_photo, weighted=False)


def blend_silhouette_normals(normals: np.ndarray, inside: np.ndarray,
                             outside_photo: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) float32 unit normals: `normals` (H, W, 3) pulled toward the silhouette's
    (`silhouette_normals`) with weight exp(-(d - 0.5) / reach), d the distance in pixels to the
    outline; unchanged outside `inside`."""
    return _over_outlined_box(np.array(normals, np.float32), np.asarray(inside, bool),
                              outside_photo, weighted=True)


def _over_outlined_box(normals, inside, outside_photo, weighted):
    """`normals` (H, W, 3) float32 with the silhouette's normals (weighted: blended in)
    written over the person's pixels, worked out on the mask's bounding box only (wide enough
    that the filters see everything they would on the whole crop). Unchanged without an
    outline."""
    side = max(inside.shape)
    radius = max(int(round(PART_RADIUS * side)), 1)
    sigma = max(GRADIENT_SIGMA * side, 1.0)
    if not inside.any():
        return normals
    box = bounding_box(inside, margin=radius + int(np.ceil(4 * sigma)) + 2)
    person = inside[box]
    solid = person if outside_photo is None else person | np.asarray(outside_photo, bool)[box]
    if solid.all():
        return normals
    distance = np.where(person, ndimage.distance_transform_edt(solid), 0.0).astype(np.float32)
    shape = _rounded_shape(distance, radius, sigma)
    if weighted:
        reach = max(REACH * side, 1.0)
        weight = np.minimum(np.exp(-(distance[person] - 0.5) / reach), 1.0)[:, None]
        shape = (1.0 - weight) * _unit(normals[box][person]) + weight * shape[person]
    else:
        shape = shape[person]
    region = normals[box]
    region[person] = _unit(shape)
    return normals


def _rounded_shape(distance: np.ndarray, radius: int, sigma: float) -> np.ndarray:
    """(h, w, 3) float32 unit normals of the rounded shape from the outline's distance map
    (h, w) (zero outside the person): parts of half-width R <= radius are round, wider ones
    have rounded sides of that radius (R is the largest distance within `radius`)."""
    half_width = np.maximum(ndimage.maximum_filter(distance, size=2 * radius + 1), 1.0)
    # out of the silhouette: down the distance map's gradient (rows grow downward, y upward)
    d_row, d_col = np.gradient(ndimage.gaussian_filter(distance, sigma))
    outward = _unit(np.stack([-d_col, d_row], axis=-1))
    # a circle's cross-section: in-plane part 1 - d / R (d from the pixel's centre, 0.5 in)
    planar = np.clip(1.0 - (distance - 0.5) / half_width, 0.0, 1.0)
    normals = np.concatenate([outward * planar[..., None],
                              np.sqrt(1.0 - planar ** 2)[..., None]], axis=-1)
    # where the outline's direction is undecided (a 1-px line: the gradient cancels) the
    # in-plane part is lost, and the normal faces the camera
    return _unit(normals)


def _unit(vectors: np.ndarray) -> np.ndarray:
    """float32 unit vectors along the last axis; zero vectors stay zero."""
    vectors = np.asarray(vectors, np.float32)
    length = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)
