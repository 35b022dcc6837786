"""Normals from the person's outline (relightcli.geometry.silhouette)."""

import numpy as np
import pytest

from relightcli.compose import CropBox, outside_photo
from relightcli.geometry.silhouette import blend_silhouette_normals, silhouette_normals


def angle_degrees(a, b):
    cosine = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def disc(side, radius, centre=None):
    """A disc's mask and the normals of the sphere it outlines (camera frame: y up)."""
    cy, cx = centre if centre is not None else (side / 2, side / 2)
    rows, cols = np.mgrid[0:side, 0:side] + 0.5
    x, y = (cols - cx) / radius, -(rows - cy) / radius
    inside = x ** 2 + y ** 2 < 1.0
    z = np.sqrt(np.clip(1.0 - x ** 2 - y ** 2, 0.0, 1.0))
    return inside, np.stack([x, y, z], axis=-1)


def test_a_small_disc_outlines_a_sphere():
    # a part narrower than PART_RADIUS (16 px at 512) is round: a disc gives a sphere's normals
    inside, sphere = disc(512, 14.0)
    normals = silhouette_normals(inside)
    error = angle_degrees(normals[inside], sphere[inside])
    assert np.median(error) < 5.0
    assert error.mean() < 8.0
    np.testing.assert_allclose(np.linalg.norm(normals[inside], axis=-1), 1.0, atol=1e-5)
    assert not normals[~inside].any()


def test_at_the_outline_normals_point_out_and_across_the_view():
    inside, _ = disc(256, 60.0)
    rows, cols = np.nonzero(inside)
    normals = silhouette_normals(inside)
    # the rightmost and topmost pixels of the disc
    right = normals[rows[np.argmax(cols)], cols.max()]
    top = normals[rows.min(), cols[np.argmin(rows)]]
    assert right[0] > 0.85 and abs(right[2]) < 0.45
    assert top[1] > 0.85 and abs(top[2]) < 0.45
    # a wide part is flat in the middle: it faces the camera
    assert normals[128, 128, 2] > 0.999


def test_the_blend_leaves_the_interior_to_the_net_and_bends_the_outline():
    inside = np.zeros((512, 512), bool)
    inside[100:400, 150:350] = True
    net = np.zeros((512, 512, 3), np.float32)
    net[..., 2] = 1.0  # a net that sees a flat front everywhere
    blended = blend_silhouette_normals(net, inside)
    np.testing.assert_allclose(blended[250, 250], [0, 0, 1], atol=1e-3)  # 100 px in
    assert blended[250, 150, 0] < -0.5  # the left edge turns left
    assert blended[250, 349, 0] > 0.5  # the right edge turns right
    assert blended[100, 250, 1] > 0.5  # the top edge turns up
    np.testing.assert_array_equal(blended[~inside], net[~inside])
    np.testing.assert_allclose(np.linalg.norm(blended[inside], axis=-1), 1.0, atol=1e-5)


def test_the_photos_edge_is_no_outline():
    # a person cut by the photo's bottom edge: the crop's rows beyond it are padding
    box = CropBox(x0=0, y0=0, size=512, resolution=512)
    beyond = outside_photo(box, height=400, width=512)
    assert beyond[400:].all() and not beyond[:400].any()
    inside = np.zeros((512, 512), bool)
    inside[200:400, 200:300] = True
    net = np.zeros((512, 512, 3), np.float32)
    net[..., 2] = 1.0
    blended = blend_silhouette_normals(net, inside, beyond)
    np.testing.assert_allclose(blended[399, 250], [0, 0, 1], atol=0.01)  # the cut: unchanged
    assert blended[200, 250, 1] > 0.5  # the head end still turns up
    without = blend_silhouette_normals(net, inside)
    assert without[399, 250, 1] < -0.5  # without the photo's edge the cut would turn down


def test_outside_photo_of_a_box_reaching_past_two_edges():
    box = CropBox(x0=-100, y0=50, size=400, resolution=200)  # 2 photo pixels per crop pixel
    beyond = outside_photo(box, height=300, width=250)
    assert beyond[:, :50].all() and not beyond[:125, 50:175].any()
    assert beyond[125:].all() and beyond[:, 175:].all()


@pytest.mark.parametrize("case", ["empty", "full", "one pixel", "sliver", "diagonal line"])
def test_degenerate_masks_give_finite_unit_normals(case):
    inside = np.zeros((64, 64), bool)
    if case == "full":
        inside[:] = True
    elif case == "one pixel":
        inside[30, 30] = True
    elif case == "sliver":
        inside[10:60, 31] = True
    elif case == "diagonal line":
        inside[np.arange(64), np.arange(64)] = True
    net = np.random.default_rng(0).normal(size=(64, 64, 3)).astype(np.float32)
    net /= np.linalg.norm(net, axis=-1, keepdims=True)
    for normals in (silhouette_normals(inside), blend_silhouette_normals(net, inside)):
        assert np.isfinite(normals).all()
        np.testing.assert_allclose(np.linalg.norm(normals[inside], axis=-1), 1.0, atol=1e-5)
    if case in ("empty", "full"):  # no outline: the net's normals as they were
        np.testing.assert_array_equal(blend_silhouette_normals(net, inside), net)
