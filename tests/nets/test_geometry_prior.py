"""The prior net's input (relightcli.nets.geometry.prior_channels) and the geometry stage's
choice between the prior net and the net from the image alone."""

from __future__ import annotations

import numpy as np

from relightcli.compose import CropBox
from relightcli.nets.geometry import PRIOR_CHANNELS, GeometryMaps, prior_channels


def ball_maps(size: int, offset: float = 0.0):
    """A ball of radius 0.6 in the [-1, 1] crop as body maps: mask, normals, depths."""
    centres = -1.0 + (np.arange(size) + 0.5) * 2.0 / size
    x, y = np.meshgrid(centres, -centres)
    r2 = x**2 + y**2
    inside = r2 < 0.36
    z = np.sqrt(np.clip(0.36 - r2, 0, None))
    front = (np.stack([x, y, z], -1) / 0.6 * inside[..., None]).astype(np.float32)
    back = front * np.array([1, 1, -1], np.float32)
    return (inside, front, back, np.where(inside, z + offset, 0).astype(np.float32),
            np.where(inside, -z + offset, 0).astype(np.float32))


def test_channels_are_the_body_with_translation_free_depths_and_zero_off_it():
    mask, front, back, front_z, back_z = ball_maps(64)
    prior = prior_channels(mask, front, back, front_z, back_z, 64)
    assert prior.shape == (64, 64, len(PRIOR_CHANNELS)) and prior.dtype == np.float32
    np.testing.assert_array_equal(prior[..., 8], mask)
    assert not prior[~mask].any()
    np.testing.assert_allclose(prior[mask][:, 0:3], front[mask], atol=1e-6)
    assert abs(prior[..., 6][mask].mean()) < 1e-6  # the mean front depth is removed
    shifted = prior_channels(mask, front, back, *ball_maps(64, offset=3.0)[3:], 64)
    np.testing.assert_allclose(shifted, prior, atol=1e-5)


def test_shrinking_keeps_normals_unit_and_edge_depths_undiluted():
    mask, front, back, front_z, back_z = ball_maps(256)
    prior = prior_channels(mask, front, back, front_z, back_z, 64)
    covered = prior[..., 8] > 0
    assert prior.shape == (64, 64, 9)
    np.testing.assert_allclose(np.linalg.norm(prior[covered][:, 0:3], axis=-1), 1.0, atol=1e-5)
    # an edge pixel half covered keeps the depth of its covered half, not half of it
    small = prior_channels(*ball_maps(64), 64)
    edge = covered & (prior[..., 8] < 0.9) & (small[..., 8] > 0.5)
    assert edge.any()
    assert np.abs(prior[..., 6][edge] - small[..., 6][edge]).max() < 0.15


def test_no_body_gives_all_zero_channels():
    zeros = np.zeros((32, 32), np.float32)
    prior = prior_channels(zeros > 0, np.zeros((32, 32, 3), np.float32), np.zeros((32, 32, 3), np.float32),
                           zeros, zeros, 16)
    assert prior.shape == (16, 16, 9) and not prior.any()


class _Net:
    trained_resolution = None

    def __init__(self, name, calls):
        self.name, self.calls = name, calls

    def predict(self, image, prior=None):
        self.calls.append((self.name, None if prior is None else prior.shape))
        size = image.shape[0]
        normal = np.zeros((size, size, 3), np.float32)
        normal[..., 2] = 1
        zeros = np.zeros((size, size), np.float32)
        return GeometryMaps(normal, -normal, zeros, zeros, zeros + 1)


class _Models:
    def __init__(self, ships_prior):
        self.ships_prior, self.calls = ships_prior, []

    def has(self, name):
        return name == "geometry_prior" and self.ships_prior

    def get(self, family):
        return _Net(family, self.calls)


def _frame(with_body):
    from relightcli.geometry.body_maps import BodyMaps
    from relightcli.stages.frame import Frame

    frame = Frame(image=np.zeros((32, 32, 3), np.float32), mask=None, env=None)
    frame.box = CropBox(x0=0, y0=0, size=32, resolution=32)
    frame.crop, frame.crop_mask = np.zeros((32, 32, 3), np.float32), np.ones((32, 32), np.float32)
    if with_body:
        mask, front, back, front_z, back_z = ball_maps(32)
        frame.body_maps = BodyMaps(mask, front_z, back_z, front, back, front=None)
    return frame


def test_the_geometry_stage_uses_the_prior_net_only_with_a_fitted_body():
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.geometry import stage_geometry

    options = RelightOptions(resolution=32)
    for with_body, ships, used, why in ((True, True, "geometry_prior", "fitted bodies"),
                                        (False, True, "geometry", "none: no converged body fit"),
                                        (True, False, "geometry", "none: no geometry_prior model")):
        frame, models = _frame(with_body), _Models(ships)
        stage_geometry(frame, options, models)
        assert [name for name, _ in models.calls] == [used, used]  # the crop and its mirror
        assert frame.notes["geometry"] == {"net": used, "prior": why}
        if used == "geometry_prior":
            assert models.calls[0][1] == models.calls[1][1] == (32, 32, 9)
        assert frame.normal.shape == (32, 32, 3)


def test_the_geometry_stage_bends_the_nets_normals_toward_the_outline_but_not_at_the_photos_edge():
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.geometry import stage_geometry

    # a person 40 px wide, cut by the photo's bottom edge (the crop reaches 32 px below it)
    frame = _frame(with_body=False)
    frame.image = np.zeros((96, 128, 3), np.float32)
    frame.box = CropBox(x0=0, y0=0, size=128, resolution=128)
    frame.crop = np.zeros((128, 128, 3), np.float32)
    frame.crop_mask = np.zeros((128, 128), np.float32)
    frame.crop_mask[20:96, 44:84] = 1.0
    stage_geometry(frame, RelightOptions(resolution=128), _Models(False))
    n = frame.normal  # the fake net sees a flat front everywhere
    assert n[60, 44, 0] < -0.5 and n[60, 83, 0] > 0.5 and n[20, 64, 1] > 0.5  # sides and top
    np.testing.assert_allclose(n[95, 64], [0, 0, 1], atol=0.02)  # the photo's edge: as the net said
    np.testing.assert_allclose(n[60, 64], [0, 0, 1], atol=0.02)  # the middle: as the net said
    assert not n[frame.crop_mask == 0].any()
