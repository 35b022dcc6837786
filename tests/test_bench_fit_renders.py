"""bench/bench_fit_renders.py's limb count: which true limbs the product's mask and mesh keep."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import bench_fit_renders as bench  # noqa: E402
from relightcli.compose import CropBox  # noqa: E402


def standing_person() -> dict:
    """Photo pixels (col, row) of the 12 main joints of a person standing in a 200 x 200 photo:
    the arms hang at columns 70 (left) and 130, the legs stand at 90 and 110."""
    rows = {"upperarm01": 60, "lowerarm01": 90, "wrist": 120, "upperleg01": 110, "lowerleg01": 150, "foot": 190}
    arm = ("upperarm01", "lowerarm01", "wrist")
    cols = {("L", True): 70.0, ("R", True): 130.0, ("L", False): 90.0, ("R", False): 110.0}
    return {f"{bone}.{side}": np.array([cols[side, bone in arm], float(row)])
            for bone, row in rows.items() for side in "LR"}


def test_a_limb_outside_the_mask_or_the_mesh_is_not_kept():
    joints = standing_person()
    mask = np.zeros((200, 200), np.float32)
    mask[50:195, 60:141] = 1.0  # the whole person
    covered = np.ones((100, 100), bool)  # the crop: the whole photo at half its resolution
    frame = SimpleNamespace(mask=mask, box=CropBox(0, 0, 200, 100), hits=SimpleNamespace(mask=covered))
    assert bench.limbs_kept(frame, joints) == {"limbs_mask": 8, "limbs_mesh": 8}
    mask[:, :95] = 0.0  # the left arm and leg cut off
    covered[:, 55:] = False  # the mesh misses the right half: the right arm and leg
    assert bench.limbs_kept(frame, joints) == {"limbs_mask": 4, "limbs_mesh": 4}


def test_points_outside_the_image_are_outside():
    mask = np.ones((10, 10), bool)
    assert bench.share_inside(mask, np.array([[5.0, 5.0], [-1.0, 5.0], [5.0, 10.0], [9.9, 9.9]])) == 0.5
