"""Readers of the MakeHuman formats: BVH, targets, rig, weights, OBJ, mhclo."""

import numpy as np
import pytest

from export.factory import assets, clothes
from export.factory.makehuman import axis_rotation, read_bvh, read_obj, read_target
from relightcli.errors import InputError

TINY_BVH = """HIERARCHY
ROOT hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT arm
  {
    OFFSET 1 0 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    End Site
    {
      OFFSET 1 0 0
    }
  }
}
MOTION
Frames: 1
Frame Time: 0.04
0 0 0 90 0 0 10 20 30
"""


def test_bvh_tiny_hierarchy_and_channel_order(tmp_path):
    path = tmp_path / "tiny.bvh"
    path.write_text(TINY_BVH)
    pose = read_bvh(path)
    assert pose.names == ("hips", "arm")
    assert list(pose.parents) == [-1, 0]
    np.testing.assert_allclose(pose.offsets[1], [1, 0, 0])
    # Zrotation 90 about z takes +x to +y.
    np.testing.assert_allclose(pose.rotations[0] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    expected = axis_rotation("x", 10) @ axis_rotation("y", 20) @ axis_rotation("z", 30)
    np.testing.assert_allclose(pose.rotations[1], expected, atol=1e-12)


def test_bvh_truncated_motion_raises(tmp_path):
    path = tmp_path / "short.bvh"
    path.write_text(TINY_BVH.replace("10 20 30", "10"))
    with pytest.raises(InputError):
        read_bvh(path)


def test_bvh_known_pose_standing01(makehuman_data):
    pose = read_bvh(assets.asset_path("poses/standing01.bvh"))
    assert len(pose.names) == 163 and pose.names[0] == "root"
    assert pose.names[pose.parents[pose.names.index("upperleg01.R")]] == "pelvis.R"
    # The file's pelvis.R channels are (0.000013, 9.754425, -0.000007) degrees (X, Y, Z).
    r = pose.rotations[pose.names.index("pelvis.R")]
    angle = np.degrees(np.arccos((np.trace(r) - 1) / 2))
    assert angle == pytest.approx(9.754425, abs=1e-4)
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 1, 0], atol=1e-6)  # a turn about Y


@pytest.mark.parametrize("axis,vector,expected", [("x", [0, 1, 0], [0, 0, 1]),
                                                  ("y", [0, 0, 1], [1, 0, 0]),
                                                  ("z", [1, 0, 0], [0, 1, 0])])
def test_axis_rotation_is_right_handed(axis, vector, expected):
    np.testing.assert_allclose(axis_rotation(axis, 90.0) @ vector, expected, atol=1e-12)


def test_target_reader_converts_to_metres(tmp_path):
    path = tmp_path / "t.target"
    path.write_text("# comment\n3 1.0 -2.0 0.5\n7 0 0 10\n")
    ids, offsets = read_target(path)
    assert list(ids) == [3, 7]
    np.testing.assert_allclose(offsets, [[0.1, -0.2, 0.05], [0, 0, 1.0]])


def test_base_mesh_groups_and_height(base):
    mesh = base.mesh
    assert mesh.vertices.shape == (19158, 3)
    body = np.unique(mesh.faces[base.body_faces])
    assert body.max() == 13379  # the body group is the first 13,380 vertices
    assert 1.5 < np.ptp(mesh.vertices[body, 1]) < 1.8  # metres
    # Facing +Z: the toes reach much farther in front of the ankle than the heel behind it.
    heads, _ = base.skeleton.joint_positions(mesh.vertices)
    ankle = heads[base.skeleton.names.index("foot.L")]
    foot = body[(mesh.vertices[body, 1] < ankle[1]) & (mesh.vertices[body, 0] > 0)]
    z = mesh.vertices[foot, 2]
    assert z.max() - ankle[2] > 2 * (ankle[2] - z.min())


def test_skin_weights_rows_sum_to_one(base):
    np.testing.assert_allclose(np.asarray(base.weights.sum(axis=1)).ravel(), 1.0, atol=1e-12)


def test_obj_reader_fans_quads(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 10 0 0\nv 10 10 0\nv 0 10 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
                    "g piece\nf 1/1 2/2 3/3 4/4\n")
    mesh = read_obj(path)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    np.testing.assert_allclose(mesh.vertices[2], [1.0, 1.0, 0.0])  # decimetres -> metres
    np.testing.assert_allclose(mesh.uvs[1], [[0, 0], [1, 1], [0, 1]])


def test_mhclo_reader_parses_single_ids_and_delete_ranges(tmp_path):
    (tmp_path / "g.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "g.mhclo").write_text(
        "name g\nobj_file g.obj\nx_scale 0 1 1.0\nverts 0\n5\n1 2 3 0.5 0.25 0.25 1 0 0\n"
        "4 5 6 1 0 0 0 0 0\ndelete_verts\n10 - 12 20\n30\n")
    garment = clothes.read_mhclo(tmp_path / "g.mhclo")
    assert garment.ids.tolist() == [[5, 5, 5], [1, 2, 3], [4, 5, 6]]
    np.testing.assert_allclose(garment.offsets[1], [0.1, 0, 0])
    assert garment.delete_verts.tolist() == [10, 11, 12, 20, 30]
    assert garment.scale_refs["x"] == (0, 1, pytest.approx(0.1))
