"""Training data made by the runtime's own stages: the coarse body shading the refinement net
refines (export/factory/coarse.py) and the face close-ups with the runtime's coarse face
shading (export/factory/face_closeups.py), plus the dataset's add_arrays they write with."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from export.factory import coarse, dataset, face_closeups, generate, lighting, render
from export.train.data import relative_depths
from relightcli.nets.geometry import GeometryMaps
from relightcli.stages.frame import Models
from relightcli.stages.geometry import mirror

RES = 64
CONFIG = generate.GenerationConfig(
    seed=3, samples_per_person=2,
    settings=render.RenderSettings(resolution=RES, spp=16, target_error=None, ao_spp=4, bounces=1))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, makehuman_data):
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip("shared HDRIs not found")
    root = tmp_path_factory.mktemp("factory")
    generate.generate(root, {"val": 2}, CONFIG)
    dataset.write_card(root, {"name": "tiny"})
    return root


@pytest.fixture
def copy(tiny, tmp_path):
    """A writable copy (the tests add arrays)."""
    return shutil.copytree(tiny, tmp_path / "data")


def test_add_arrays_keeps_the_stored_bytes_and_merges_the_metadata(tmp_path):
    shading = np.random.default_rng(0).uniform(0, 5, (8, 8, 3)).astype(np.float32)
    dataset.write_sample(tmp_path, "val", "000000", {"shading_b": shading, "mask": np.ones((8, 8))}, {"a": 1})
    before = dict(np.load(dataset.sample_path(tmp_path, "val", "000000")))
    dataset.add_arrays(tmp_path, "val", "000000", {"coarse_shading_b": 2 * shading}, {"b": 2})
    after = np.load(dataset.sample_path(tmp_path, "val", "000000"))
    for name in before:
        if name != "__meta__":
            assert np.array_equal(before[name], after[name]), name
    dataset.write_card(tmp_path, {})
    data = dataset.open_dataset(tmp_path)
    assert data.meta("val", "000000") == {"a": 1, "b": 2}
    np.testing.assert_allclose(data.load("val", "000000")["coarse_shading_b"], 2 * shading, rtol=1e-3)


class TrueGeometry(Models):
    """The sample's own geometry as the geometry net's answer: the coarse shading then differs
    from the rendered shading only by the reconstruction (meshing, smoothing) and noise."""

    def __init__(self, sample):
        super().__init__(threads=1)
        front, back = relative_depths(sample)
        mask = sample["mask"]
        maps = GeometryMaps(sample["normal"], sample["back_normal"], front, back, mask)
        self._sessions["geometry"] = TrueNet(maps)
        self._sessions["ao"] = type("Net", (), {"predict": lambda self, image: sample["ao"]})()


class TrueNet:
    """Answers `maps` for the first crop it is given and the mirrored maps for that crop's
    mirror image, as a net that knew the truth would (the geometry stage averages the two)."""

    def __init__(self, maps):
        self.maps, self.crop = maps, None

    def predict(self, image):
        if self.crop is not None and np.array_equal(image, mirror(self.crop)):
            m = self.maps
            return GeometryMaps(mirror(m.front_normal, (0,)), mirror(m.back_normal, (0,)), mirror(m.front_depth),
                                mirror(m.back_depth), mirror(m.mask))
        self.crop = image
        return self.maps


def test_coarse_shading_of_the_true_geometry_matches_the_rendered_shading(tiny, stand_in_normals):
    data = dataset.open_dataset(tiny)
    for sample_id in data.ids("val"):
        sample, meta = data.load("val", sample_id), data.meta("val", sample_id)
        arrays, stats = coarse.coarse_arrays(sample, meta, TrueGeometry(sample), bodies=False)
        inside = sample["mask"] > 0.5
        got, want = arrays["coarse_shading_b"], sample["shading_b"]
        assert got.shape == want.shape and np.all(np.isfinite(got)) and np.all(got >= 0)
        # Same lighting, exposure and units: the typical pixel agrees closely. (The mean does
        # not: the smoothed mesh moves sun shadows, and one moved shadow edge shifts the mean
        # by 10-25 %. At 256 px on 8 factory samples the median ratio was 0.94-1.00.)
        ratio = np.median(got[inside] / np.maximum(want[inside], 1e-6))
        assert 0.9 < ratio < 1.1, (sample_id, ratio)
        assert np.all(got[~inside] == 0)
        assert np.array_equal(arrays["ao_pred"], sample["ao"]) and stats["spp_mean"] > 0
        np.testing.assert_allclose(arrays["normal_pred"], sample["normal"] * inside[..., None], atol=1e-6)


def test_coarse_run_adds_arrays_once_per_model_set(copy):
    assert coarse.run(copy, ["val"], workers=1) == 2
    data = dataset.open_dataset(copy)
    for sample_id in data.ids("val"):
        sample = data.load("val", sample_id)
        assert sample["coarse_shading_b"].shape == (RES, RES, 3) and sample["ao_pred"].shape == (RES, RES)
        assert data.meta("val", sample_id)["coarse"]["geometry"] == coarse.models_record()["geometry"]
    assert coarse.run(copy, ["val"], workers=1) == 0  # resumed: nothing left to do


def test_normals_only_adds_the_geometry_nets_normals_without_ray_tracing(copy):
    assert coarse.run(copy, ["val"], workers=1, product="normals") == 2
    data = dataset.open_dataset(copy)
    for sample_id in data.ids("val"):
        sample, meta = data.load("val", sample_id), data.meta("val", sample_id)
        assert "coarse_shading_b" not in sample and "coarse" not in meta
        normal, inside = sample["normal_pred"], sample["mask"] > 0.5
        np.testing.assert_allclose(np.linalg.norm(normal[inside], axis=-1), 1.0, atol=2e-3)
        assert np.all(normal[~inside] == 0)
        assert meta["normals"] == coarse.models_record("normals")
    assert coarse.run(copy, ["val"], workers=1, product="normals") == 0


def test_head_square_is_the_face_box_times_the_margin_in_world_units():
    # a 10 x 20 px face box in a 100 px image spanning [0, 2] x [0, 2]: 0.02 world units per px
    rect = face_closeups.closeup_rect([40, 30, 50, 50], (0.0, 2.0, 0.0, 2.0), 100, margin=1.6)
    np.testing.assert_allclose(rect, (0.9 - 0.32, 0.9 + 0.32, 1.2 - 0.32, 1.2 + 0.32))


def test_square_in_pixels_inverts_the_world_square():
    rect = face_closeups.closeup_rect([40, 30, 50, 50], (0.0, 2.0, 0.0, 2.0), 100, margin=1.6)
    centre_x, centre_y, side = face_closeups.square_in_pixels(rect, (0.0, 2.0, 0.0, 2.0), 100)
    np.testing.assert_allclose((centre_x, centre_y, side), (45.0, 40.0, 32.0))


def test_runtime_view_loses_detail_but_keeps_the_mean():
    image = np.random.default_rng(1).uniform(0, 1, (128, 128, 3)).astype(np.float32)
    seen = face_closeups.runtime_view(image, 48)
    assert seen.shape == image.shape
    assert abs(seen.mean() - image.mean()) < 0.01 and seen.std() < 0.5 * image.std()


def test_closeups_hold_the_face_path_inputs_and_target(copy, tmp_path):
    out = tmp_path / "closeups"
    assert face_closeups.run(copy, out, ["val"], workers=1)["counts"]["val"] == 0  # waits for the coarse shading
    card = face_closeups.run(copy, out, ["val"], workers=1, body_input="truth")
    data = dataset.open_dataset(out)
    assert card["counts"]["val"] == len(data.ids("val"))
    assert data.ids("val"), "the runtime's face fit refused every tiny sample"
    sample = data.load("val", data.ids("val")[0])
    for name in ("shading_b", "coarse_face_b", "body_shading_b"):
        assert sample[name].shape == (128, 128, 3) and np.all(np.isfinite(sample[name])), name
    face = sample["face_pixels"] > 0.5
    assert face.sum() > 500  # the fitted face fills a good part of the crop
    # the face is lit (but for the mouth's slit and the nostrils, which see no sky)
    assert np.mean(sample["coarse_face_b"][face].sum(axis=-1) > 0) > 0.99
    # the target and the coarse face shading are in the same units: a few x apart at most
    ratio = np.median(sample["coarse_face_b"][face]) / np.median(sample["shading_b"][face])
    assert 0.3 < ratio < 3.0


def test_the_prior_maps_are_the_runtimes_own():
    """export.factory.coarse --priors makes a sample's prior maps with the runtime's stages:
    on the T-pose render they equal the body maps `relight` itself computes for that photo and
    its mask at the same resolution, and the prior net's input is built from them by the
    runtime's prior_channels."""
    import cv2

    from relightcli import compose
    from relightcli.batch import ItemReport
    from relightcli.io.images import read_image
    from relightcli.nets.geometry import prior_channels
    from relightcli.pipeline import RelightOptions, run_stages
    from relightcli.stages.body import body_shading_pixels
    from relightcli.stages.geometry import body_ao

    data = Path(__file__).resolve().parents[1] / "data"
    photo = read_image(data / "tpose_render.png").rgb
    mask = (cv2.imread(str(data / "tpose_render_mask.png"), cv2.IMREAD_GRAYSCALE) > 127).astype(np.float32)
    # the sample is the runtime's working crop of the photo (a factory sample is one), so the
    # runtime's own crop of it is the whole of it
    box = compose.person_crop_box(mask, 256)
    image, mask = compose.crop_square(photo, box), (compose.crop_square(mask, box) > 0.5).astype(np.float32)
    assert compose.person_crop_box(mask, 256) == compose.CropBox(0, 0, 256, 256)
    arrays, stats = coarse.prior_arrays({"input": image, "mask": mask}, {}, Models(threads=1))
    assert stats["converged"] == 1
    options = RelightOptions(outputs=("body_normal",), resolution=256, threads=1)
    frame, _ = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("tpose"))
    maps = frame.body_maps
    assert np.array_equal(arrays["prior_mask"], maps.mask.astype(np.float32))
    for key, ours in (("prior_normal", maps.front_normal), ("prior_back_normal", maps.back_normal),
                      ("prior_front_depth", maps.front_depth), ("prior_back_depth", maps.back_depth)):
        assert np.array_equal(arrays[key], ours), key
    prior = prior_channels(arrays["prior_mask"], arrays["prior_normal"], arrays["prior_back_normal"],
                           arrays["prior_front_depth"], arrays["prior_back_depth"], 128)
    assert prior.shape == (128, 128, 9) and np.isfinite(prior).all()
    assert (prior[..., 8] > 0.5).mean() > 0.1
    # --prior-ao: the same maps, and the bodies' AO as the runtime traces it
    with_ao, _ = coarse.prior_ao_arrays({"input": image, "mask": mask}, {}, Models(threads=1))
    assert all(np.array_equal(with_ao[key], arrays[key]) for key in arrays)
    traced = body_ao(frame, options.seed) * body_shading_pixels(frame)
    assert np.array_equal(with_ao["prior_ao"], traced)
    person = mask > 0.5
    assert 0.5 < with_ao["prior_ao"][person].mean() < 1.0  # open on the whole, darker in places


def test_a_sample_without_a_person_found_gets_empty_priors():
    sample = {"input": np.zeros((64, 64, 3), np.float32), "mask": np.zeros((64, 64), np.float32)}
    arrays, stats = coarse.prior_arrays(sample, {}, Models(threads=1))
    assert stats["people"] == 0 and stats["converged"] == 0
    assert not arrays["prior_mask"].any() and not arrays["prior_normal"].any()
    assert arrays["prior_normal"].shape == (64, 64, 3)
    arrays, _ = coarse.prior_ao_arrays(sample, {}, Models(threads=1))
    assert arrays["prior_ao"].shape == (64, 64) and not arrays["prior_ao"].any()
