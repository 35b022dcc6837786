"""The geometry and de-lighting nets' maps averaged with their maps of the mirrored crop
(relightcli.stages.geometry.MIRROR_AVERAGED): the mirror conventions of images, normals and lights."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from relightcli.io.envmap import texel_directions
from relightcli.io.images import read_image
from relightcli.nets.geometry import GeometryMaps
from relightcli.stages.frame import Models, unit
from relightcli.stages.geometry import average_geometry, mirror

TPOSE = Path(__file__).resolve().parents[1] / "data" / "tpose_render.png"


def test_a_mirrored_light_holds_the_mirrored_directions():
    directions = texel_directions(16, 32)
    np.testing.assert_allclose(mirror(directions * np.array([-1.0, 1.0, 1.0])), directions, atol=1e-12)
    light = np.zeros((16, 32, 3), np.float32)
    light[5, 24] = 1.0  # a texel to the camera's right (+x)
    mirrored = mirror(light)
    (row, col), = np.argwhere(mirrored[..., 0] > 0)
    np.testing.assert_allclose(directions[row, col], directions[5, 24] * [-1.0, 1.0, 1.0], atol=1e-12)


def test_mirroring_negates_the_x_of_the_named_vectors_only():
    image = np.random.default_rng(0).random((4, 6, 7)).astype(np.float32)
    out = mirror(image, (0, 3))
    np.testing.assert_array_equal(out[:, ::-1][..., [0, 3]], -image[..., [0, 3]])
    np.testing.assert_array_equal(out[:, ::-1][..., [1, 2, 4, 5, 6]], image[..., [1, 2, 4, 5, 6]])
    np.testing.assert_array_equal(mirror(mirror(image, (0, 3)), (0, 3)), image)
    np.testing.assert_array_equal(mirror(image[..., 0]), image[:, ::-1, 0])


def relief_net(image: np.ndarray) -> GeometryMaps:
    """A stand-in geometry net that sees the image as a height field: normals from its
    gradients (so it is equivariant: the mirrored image gives the mirrored normals)."""
    height = image.mean(axis=2)
    dy, dx = np.gradient(height)
    front = unit(np.stack([-dx, dy, np.full_like(dx, 0.2)], axis=-1))
    return GeometryMaps(front_normal=front, back_normal=front * np.array([1, 1, -1], np.float32),
                        front_depth=height, back_depth=-height, mask=(height > 0.5).astype(np.float32))


def test_an_equivariant_nets_maps_are_unchanged_by_the_average():
    image = cv2.GaussianBlur(np.random.default_rng(1).random((32, 32, 3)).astype(np.float32), (5, 5), 2)
    direct = relief_net(image)
    averaged = average_geometry(direct, relief_net(mirror(image)))
    for name in ("front_normal", "back_normal", "front_depth", "back_depth", "mask"):
        np.testing.assert_allclose(getattr(averaged, name), getattr(direct, name), atol=1e-5, err_msg=name)


def test_the_shipped_geometry_net_agrees_with_itself_on_the_mirrored_crop():
    """The x of the mirrored crop's normals is negated back: they then agree with the crop's
    own within ~11 degrees, and would be ~50 degrees off if it were not."""
    image = read_image(TPOSE).rgb
    side = max(image.shape[:2])
    square = np.zeros((side, side, 3), np.float32)
    top, left = (side - image.shape[0]) // 2, (side - image.shape[1]) // 2
    square[top:top + image.shape[0], left:left + image.shape[1]] = image
    crop = cv2.resize(square, (256, 256), interpolation=cv2.INTER_AREA)
    net = Models(1).get("geometry")
    direct, mirrored = net.predict(crop), net.predict(mirror(crop))
    person = direct.mask > 0.5

    def mean_angle(a, b):
        return float(np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1, 1)))[person].mean())

    assert person.mean() > 0.05
    assert mean_angle(direct.front_normal, mirror(mirrored.front_normal, (0,))) < 20.0
    assert mean_angle(direct.front_normal, mirror(mirrored.front_normal)) > 35.0
