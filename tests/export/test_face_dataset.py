"""The synthetic face-landmark data: the sampled distribution, ground truth aligned with the
renderer's pixels, determinism across worker counts, the shard reader, and the trainer on it
(train a few steps, export, load through the runtime class)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from export.factory import camera_model, face_dataset, faces, lighting
from relightcli.geometry.face_model import FaceModel, rotation_matrix, transform, world_to_pixel
from relightcli.render import Scene


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


@pytest.fixture(scope="module")
def hdris():
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip(f"HDRIs not found in {lighting.hdri_dir()}")
    return lighting.hdri_splits()


def test_sampled_shapes_and_poses_stay_in_their_ranges(model, hdris):
    for index in range(30):
        spec = faces.sample_spec(np.random.default_rng([0, 0, index]), model, hdris["train"])
        assert all(abs(a) <= limit for a, limit in zip(spec.angles_deg, faces.POSE_LIMITS_DEG))
        assert np.abs(spec.identity).max() <= faces.IDENTITY_CLIP
        expression = np.asarray(spec.expression)
        assert expression.min() >= 0 and expression.max() <= 1 and np.count_nonzero(expression) <= 4
        assert spec.light.kind == "sky" or spec.light.name in hdris["train"]


def test_same_seed_same_spec(model, hdris):
    a = faces.sample_spec(np.random.default_rng([1, 2, 3]), model, hdris["val"])
    b = faces.sample_spec(np.random.default_rng([1, 2, 3]), model, hdris["val"])
    assert a == b


def test_landmarks_follow_the_pixel_convention_of_the_renderer(model, hdris):
    # Frontal face: the nose-tip landmark's pixel sees the nose tip (the front-most point)
    spec = faces.sample_spec(np.random.default_rng(5), model, hdris["train"])
    spec = dataclasses.replace(spec, angles_deg=(0.0, 0.0, 0.0), expression=(0.0,) * model.n_expression)
    sample = faces.render_face(model, spec)
    vertices, landmarks = faces.posed_face(model, spec)
    rect = tuple(float(v) for v in sample["rect"])
    np.testing.assert_allclose(sample["landmarks"], world_to_pixel(landmarks, rect, (128, 128)), atol=1e-4)
    geometry, _, _ = faces.trace_surface(Scene(vertices, model.triangles), rect, 128)
    col, row = np.rint(sample["landmarks"][30]).astype(int)
    depth = geometry.position[..., 2] + Scene(vertices, model.triangles).centre[2]
    pixel = (rect[1] - rect[0]) / 128
    assert geometry.mask[row, col] and abs(depth[row, col] - landmarks[30, 2]) < pixel
    assert depth[row, col] >= depth[geometry.mask].max() - 2 * pixel


def test_generation_is_the_same_for_any_worker_count(tmp_path, hdris):
    one = face_dataset.generate(tmp_path / "one", {"train": 3, "test": 1}, seed=4, workers=1)
    two = face_dataset.generate(tmp_path / "two", {"train": 3, "test": 1}, seed=4, workers=2)
    assert one["splits"]["train"]["count"] == two["splits"]["train"]["count"] == 3
    for split in ("train", "test"):
        a = face_dataset.FaceLandmarkDataset(tmp_path / "one").arrays(split)
        b = face_dataset.FaceLandmarkDataset(tmp_path / "two").arrays(split)
        for name in face_dataset.ARRAYS:
            np.testing.assert_array_equal(a[name], b[name])
    card = json.loads((tmp_path / "one" / face_dataset.CARD_NAME).read_text())
    assert card["sources"]["face_model"]["sha256"] and "licenses" in card["sources"]


def test_reader_gives_linear_images_and_pixel_landmarks(tmp_path, hdris):
    face_dataset.generate(tmp_path, {"val": 2}, seed=0, workers=1)
    dataset = face_dataset.FaceLandmarkDataset(tmp_path)
    assert dataset.ids("val") == ["000000", "000001"] and dataset.ids("train") == []
    sample = dataset.load("val", "000001")
    raw = dataset.arrays("val")["image"][1]
    np.testing.assert_allclose(sample["image"], camera_model.decode_photo(raw))
    assert sample["image"].shape == (128, 128, 3) and sample["landmarks"].shape == (68, 2)
    # the face fills a good part of the crop but not more than it
    extent = sample["landmarks"].max(axis=0) - sample["landmarks"].min(axis=0)
    assert 128 / faces.FRAMING["scale"][1] - 1 <= extent.max() <= 128 / faces.FRAMING["scale"][0] + 1


def test_landmark_net_trains_exports_and_runs_in_the_runtime(tmp_path, hdris):
    pytest.importorskip("torch")
    from export.train.cli import main as train_main
    from relightcli.nets.landmarks import LandmarkNet

    face_dataset.generate(tmp_path / "data", {"train": 4, "val": 2}, seed=0, workers=1)
    code = train_main(["landmarks", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "run"),
                       "--steps", "2", "--threads", "1", "--set", "batch_size=2",
                       "--set", "val_max_samples=2", "--export-to", str(tmp_path / "models")])
    assert code == 0
    entry = json.loads((tmp_path / "models" / "manifest.json").read_text())["models"]["landmarks"]
    assert entry["inputs"][0]["shape"] == ["N", 3, 128, 128] and entry["parity_max_abs"] <= 1e-4
    assert set(entry["metrics"]) >= {"error_px", "nme", "split"}
    net = LandmarkNet(models_dir=tmp_path / "models", threads=1)
    points = net.predict(np.full((128, 128, 3), 0.4, np.float32))
    assert points.shape == (68, 2) and np.all(np.isfinite(points))


def test_interocular_distance_of_a_frontal_face(model):
    points = transform(model.landmarks(), 1.0, rotation_matrix(0, 0, 0), np.zeros(3))
    pixels = world_to_pixel(points, (-10, 10, -10, 10), (128, 128))
    expected = np.linalg.norm(points[36, :2] - points[45, :2]) * 128 / 20
    assert faces.interocular_px(pixels) == pytest.approx(expected)
