"""bench/by_pose.py: a report's scenes grouped by pose, failures counted but not averaged."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import by_pose  # noqa: E402


def scene(name, normal, shading, relit=18.0, albedo=19.0, error=None):
    entry = {"scene": name, "error": error}
    if error is None:
        entry.update(normal={"deg": normal}, shading={"psnr": shading}, relit={"psnr": relit}, albedo={"psnr": albedo})
    return entry


def test_groups_by_pose_and_skips_failures(tmp_path):
    for name, pose in (("a", "tpose"), ("b", "tpose"), ("c", "fly02"), ("d", "fly02")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "scene.json").write_text(json.dumps({"person": {"pose": pose}}))
    report = {"per_scene": [scene("a", 10.0, 20.0), scene("b", 20.0, 22.0), scene("c", 40.0, 14.0),
                            scene("d", None, None, error="nobody found")]}
    out = by_pose.by_pose(report, tmp_path)
    assert out["tpose"][:2] == (2, 2) and out["tpose"][2][:2] == pytest.approx([15.0, 21.0])
    assert out["fly02"][:2] == (2, 1) and out["fly02"][2][:2] == pytest.approx([40.0, 14.0])


def test_reads_an_oracle_report_row_by_row(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "scene.json").write_text(json.dumps({"person": {"pose": "tpose"}}))
    report = {"scenes": [{"scene": "a", "true mask": {"relit": 18.0, "albedo": 19.0, "shading": 20.0, "normal_deg": 17.0},
                          "true albedo": {"relit": 23.0, "shading": 20.0, "normal_deg": 17.0, "albedo": None}}]}
    assert by_pose.by_pose(report, tmp_path, "true mask")["tpose"] == (1, 1, [17.0, 20.0, 18.0, 19.0])
    count, scored, means = by_pose.by_pose(report, tmp_path, "true albedo")["tpose"]
    assert (count, scored, means[2]) == (1, 1, 23.0)


def test_reads_the_fit_s_report(tmp_path):
    for name, pose in (("a", "tpose"), ("b", "tpose"), ("c", "fly02")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "scene.json").write_text(json.dumps({"person": {"pose": pose}}))
    report = {"summary": {}, "scenes": [
        {"scene": "a", "3d_cm": 10.0, "depth_cm": 8.0, "2d_cm": 3.0, "yaw_deg": 4.0},
        {"scene": "b", "3d_cm": 14.0, "depth_cm": 12.0, "2d_cm": 5.0, "yaw_deg": 8.0},
        {"scene": "c", "skipped": "nobody fitted"}]}
    out = by_pose.fit_by_pose(report, tmp_path)
    assert out["tpose"] == (2, 2, [12.0, 10.0, 4.0, 6.0])
    assert out["fly02"][:2] == (1, 0)
