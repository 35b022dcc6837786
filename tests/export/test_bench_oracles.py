"""bench/oracles.py's true body: placed in the crop as the render placed the person, and its
landmarks given in BlazePose's world frame."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import oracles  # noqa: E402

from export.body_model import true_world_landmarks  # noqa: E402
from export.factory.person import naked_body  # noqa: E402
from relightcli.compose import CropBox  # noqa: E402
from relightcli.geometry.body_fit import blazepose_world_to_model  # noqa: E402
from relightcli.geometry.body_model import LANDMARK_NAMES  # noqa: E402


@pytest.fixture(scope="module")
def body(base):
    return naked_body(7, "train")


def meta(yaw_deg: float) -> dict:
    return {"person": {"seed": 7, "split": "train"}, "settings": {"resolution": 64},
            "spec": {"pitch_deg": 0.0, "yaw_deg": yaw_deg}}


def torso_yaw(world: np.ndarray) -> float:
    """Degrees about the vertical of the model-frame torso's forward direction, 0 at the camera."""
    points = blazepose_world_to_model(world)
    index = {name: LANDMARK_NAMES.index(name) for name in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")}
    left = points[index["left_hip"]] - points[index["right_hip"]]
    up = points[index["left_shoulder"]] + points[index["right_shoulder"]] - points[index["left_hip"]] - points[index["right_hip"]]
    forward = np.cross(left, up)
    return float(np.degrees(np.arctan2(forward[0], forward[2])))


def test_the_true_landmarks_turn_with_the_camera_and_are_hip_centred(body):
    straight, turned = (true_world_landmarks(body, meta(yaw)) for yaw in (0.0, 30.0))
    hips = [LANDMARK_NAMES.index("left_hip"), LANDMARK_NAMES.index("right_hip")]
    np.testing.assert_allclose(turned[hips].mean(axis=0), 0.0, atol=1e-9)
    assert turned[LANDMARK_NAMES.index("nose"), 1] < -0.3  # y down: the head, above the hips, is negative
    turn = (torso_yaw(turned) - torso_yaw(straight) + 180.0) % 360.0 - 180.0
    assert abs(turn - 30.0) < 0.5  # as the render turned the person (bench_fit_renders.yaw_deg)


def test_the_true_body_fills_the_crop_as_the_render_placed_it(body):
    # a render 64 px wide over 2 m, the crop the square of photo pixels 8..56: 2 crop units
    rect = np.array([-1.0, 1.0, -0.1, 1.9])
    crop = oracles.true_body_in_crop(body, meta(0.0), rect, CropBox(8, 4, 48, 64), 64)
    used = np.unique(body.faces)
    # 64 px over 2 m; 48 px of the photo span the crop's 2 units: 1 m -> 32 px -> 4/3 units
    np.testing.assert_allclose(np.ptp(crop[used, 1]), np.ptp(body.vertices[used, 1]) * 4 / 3, rtol=1e-6)
    np.testing.assert_allclose(np.ptp(crop[used, 2]), np.ptp(body.vertices[used, 2]) * 4 / 3, rtol=1e-6)
    top = body.vertices[used, 1].max()  # y = 1.9 m is photo row 0, 4 rows above the crop's top
    np.testing.assert_allclose(crop[used, 1].max(), 1.0 - ((1.9 - top) * 32 - 4) * 2 / 48, rtol=1e-6)


def test_the_true_ao_replaces_the_nets_map_over_the_true_mask_only():
    class Frame:
        box = CropBox(0, 0, 8, 8)

    def net_stage(frame, options, models):
        frame.ao_net = np.full((8, 8), 0.5, np.float32)
        frame.ao = frame.ao_net

    mask = np.zeros((8, 8), np.float32)
    mask[2:6, 3:5] = 1.0
    truth = {"mask": mask, "ao": np.full((8, 8), 0.9, np.float32)}
    frame = Frame()
    oracles.with_true_ao(net_stage, truth)(frame, None, None)
    np.testing.assert_allclose(frame.ao_net[mask > 0], 0.9)
    np.testing.assert_allclose(frame.ao_net[mask == 0], 0.5)
    assert frame.ao is frame.ao_net
