"""The landmark lifter (relightcli.nets.lift, export/lift.py): its features do not depend on where
the person stands in the photo or how large, the mirror is its own inverse, an untrained lifter
leaves BlazePose's landmarks as they are, and the runtime's ONNX answers what torch answers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relightcli.nets.lift import FEATURES, MIRROR, features, image_depths, mirrored

torch = pytest.importorskip("torch")


def pose(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    world = rng.normal(scale=0.3, size=(33, 3))
    landmarks = np.c_[200 + 400 * world[:, :2], 400 * world[:, 2], rng.random((33, 2))]
    return landmarks, world


def test_features_ignore_where_the_person_stands_and_how_large():
    landmarks, world = pose()
    moved = landmarks.copy()
    moved[:, :3] *= 2.5
    moved[:, :2] += [130.0, -40.0]
    assert features(landmarks, world).shape == (FEATURES,)
    np.testing.assert_allclose(features(moved, world), features(landmarks, world), atol=1e-5)


def test_the_mirror_swaps_sides_and_is_its_own_inverse():
    landmarks, world = pose()
    assert sorted(MIRROR) == list(range(33)) and (MIRROR[MIRROR] == np.arange(33)).all()
    once = mirrored(landmarks, world)
    np.testing.assert_array_equal(once[1][11], world[12] * [-1, 1, 1])  # left shoulder <- right
    twice = mirrored(*once)
    np.testing.assert_array_equal(twice[0], landmarks)
    np.testing.assert_array_equal(twice[1], world)


def test_image_depths_are_the_worlds_in_the_landmarks_pixels():
    landmarks, world = pose()
    out = image_depths(landmarks, world)
    ratio = np.ptp(landmarks[:, :2], axis=0).max() / np.ptp(world[:, :2], axis=0).max()
    np.testing.assert_allclose(out[:, 2], world[:, 2] * ratio)
    np.testing.assert_array_equal(out[:, [0, 1, 3, 4]], landmarks[:, [0, 1, 3, 4]])


def pairs_file(folder, split: str, count: int, seed: int) -> None:
    """Pairs whose truth is BlazePose's world landmarks with the depth doubled."""
    rows = [pose(seed + i) for i in range(count)]
    landmarks = np.stack([r[0] for r in rows])
    world = np.stack([r[1] for r in rows])
    np.savez(folder / f"fake_{split}.npz", ids=np.array([f"{i:06d}" for i in range(count)]),
             landmarks=landmarks, world=world, true=world * [1.0, 1.0, 2.0], pose=np.array(["tpose"] * count))


def test_a_lifter_learns_and_its_onnx_answers_as_torch(tmp_path, monkeypatch):
    import shutil

    from export import lift
    from relightcli.nets.lift import Lifter

    pairs_file(tmp_path, "train", 512, 0)
    pairs_file(tmp_path, "val", 16, 1000)
    metrics = lift.train(tmp_path, tmp_path / "run", width=32, epochs=60, lr=3e-3)
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[0]["cm_blazepose"] == pytest.approx(metrics["best"]["cm_blazepose"])
    assert metrics["best"]["cm"] < 0.5 * metrics["best"]["cm_blazepose"]  # it learns the doubled depth
    models = tmp_path / "models"
    shutil.copytree("models", models, ignore=shutil.ignore_patterns("*.onnx", "*.npz"))
    lift.export(tmp_path / "run", models)
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(models))
    landmarks, world = pose(2000)
    net = lift.make_net(32)
    net.load_state_dict(torch.load(tmp_path / "run" / "lift.pt"))
    net.eval()
    with torch.no_grad():
        corrections = [net(torch.from_numpy(features(*p)[None])).numpy().reshape(33, 3)
                       for p in ((landmarks, world), mirrored(landmarks, world))]
    expected = world + 0.5 * (corrections[0] + corrections[1][MIRROR] * [-1.0, 1.0, 1.0])
    np.testing.assert_allclose(Lifter(threads=1).lift(landmarks, world), expected, atol=1e-5)


def test_an_untrained_lifter_leaves_the_landmarks(tmp_path):
    from export import lift

    net = lift.make_net(16)
    landmarks, world = pose()
    with torch.no_grad():
        assert not net(torch.from_numpy(features(landmarks, world)[None])).any()
