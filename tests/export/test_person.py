"""build_person: determinism, splits, units, labels and albedo ranges."""

import numpy as np
import pytest

from export.factory import PART_NAMES, SPLITS, build_person, splits
from relightcli.errors import UsageError


@pytest.fixture(scope="module")
def person(base):
    return build_person(7, "train")


def test_build_person_is_deterministic(person):
    again = build_person(7, "train")
    np.testing.assert_array_equal(again.vertices, person.vertices)
    np.testing.assert_array_equal(again.faces, person.faces)
    np.testing.assert_array_equal(again.texture, person.texture)
    assert again.metadata == person.metadata


def test_other_split_gives_another_person(person):
    other = build_person(7, "test")
    assert other.metadata["shape"] != person.metadata["shape"]
    assert other.metadata["pose"] in splits()["pose"]["test"]


@pytest.mark.parametrize("category", ["pose", "suit_female", "suit_male", "shoes", "hair", "hat"])
def test_splits_are_disjoint_and_cover_the_catalogue(category):
    from export.factory.person import CATALOGUE

    lists = splits()[category]
    sets = [set(lists[s]) for s in SPLITS]
    assert sum(len(s) for s in sets) == len(set().union(*sets)) == len(CATALOGUE[category])
    assert lists["train"], "train must never be empty"


def test_outfit_comes_from_the_split(person):
    lists = splits()
    outfit = person.metadata["outfit"]
    assert outfit["hair"].split("/", 1)[1] in lists["hair"]["train"]
    suit = outfit["suit"].split("/", 1)[1]
    assert suit in lists["suit_female"]["train"] + lists["suit_male"]["train"]


def test_units_and_placement(person):
    v = person.vertices
    assert v.dtype == np.float32 and person.faces.dtype == np.int32
    assert v[:, 1].min() == pytest.approx(0.0, abs=1e-6)  # feet on the ground
    # Metres: posed (sitting, kneeling or a handstand) the top is below stature + raised arms.
    assert 0.4 < v[:, 1].max() < person.metadata["stature_m"] + 0.5
    assert np.abs(v[:, [0, 2]]).max() < 1.5
    assert person.faces.max() < len(v) and person.faces.min() >= 0


def test_the_true_skeleton_sits_inside_the_posed_body(person):
    from export.factory.person import base_model

    names = base_model().skeleton.names
    assert person.joints.shape == (len(names), 3) and person.joints.dtype == np.float32
    # in the vertices' frame: each main joint lies within a few cm of the posed surface
    for bone in ("upperarm01.L", "lowerarm01.R", "wrist.L", "upperleg01.R", "lowerleg01.L", "foot.R", "head"):
        gap = np.linalg.norm(person.vertices - person.joints[names.index(bone)], axis=1).min()
        assert gap < 0.12, bone
    lo, hi = person.vertices.min(axis=0), person.vertices.max(axis=0)
    assert np.all(person.joints >= lo - 0.01) and np.all(person.joints <= hi + 0.01)


def test_albedo_in_unit_range(person):
    assert person.texture.dtype == np.float32 and person.vertex_albedo.dtype == np.float32
    assert person.texture.min() >= 0 and person.texture.max() <= 1
    assert person.vertex_albedo.min() >= 0 and person.vertex_albedo.max() <= 1
    assert person.face_uv.min() >= 0 and person.face_uv.max() <= 1


def test_every_part_is_present(person):
    present = set(np.unique(person.face_part))
    assert present == set(range(len(PART_NAMES)))


def test_face_region_is_on_the_head(person):
    face = person.vertices[person.face_vertex_ids]
    assert len(face) > 100
    # Skin vertices only, and in the upper part of the body's height span (posed, so loose).
    skin = np.unique(person.faces[person.face_part == 0])
    assert np.isin(person.face_vertex_ids, skin).all()
    assert np.ptp(face, axis=0).max() < 0.35


@pytest.mark.parametrize("seed,split", [(-1, "train"), (0, "holdout")])
def test_bad_requests_raise(seed, split):
    with pytest.raises(UsageError):
        build_person(seed, split)


def test_naked_body_lies_under_the_clothes(person):
    """The body a perfect fit would find: posed and placed as the clothed person, its skin
    where the person's skin shows, nowhere farther than a garment's thickness from the person."""
    from scipy.spatial import cKDTree

    from export.factory.person import naked_body

    body = naked_body(7, "train")
    used = np.unique(body.faces)
    assert used[0] == 0 and used[-1] == len(used) - 1
    distance, _ = cKDTree(person.vertices).query(body.vertices[used])
    assert (distance < 1e-5).mean() > 0.5  # the skin the clothes leave bare is the same skin
    assert distance.max() < 0.1
    unplaced = naked_body(7, "train", placed=False)  # the same body, moved as a whole
    shift = body.vertices[used] - unplaced.vertices[used]
    np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-5)


def test_pose_variety_zero_keeps_the_people_of_before(person):
    """The fifth random stream (pose mixing) leaves the first four as they were: a
    SeedSequence's children depend on their index alone."""
    four = [np.random.default_rng(s).random(3) for s in np.random.SeedSequence([7, 0]).spawn(4)]
    five = [np.random.default_rng(s).random(3) for s in np.random.SeedSequence([7, 0]).spawn(5)[:4]]
    np.testing.assert_array_equal(four, five)
    assert "pose_mix" not in person.metadata
    np.testing.assert_array_equal(build_person(7, "train", 0.0).vertices, person.vertices)


@pytest.mark.parametrize("split", ["train", "val"])
def test_mixed_poses_stay_in_their_split(base, split):
    from export.factory.person import LIMB_GROUPS

    mixed = [build_person(seed, split, 1.0) for seed in range(4)]
    for person in mixed:
        donors = person.metadata["pose_mix"]
        assert donors and set(donors) <= set(LIMB_GROUPS)
        assert {name.split(" ")[0] for name in donors.values()} <= set(splits()["pose"][split])
        # a whole body still: on the ground, every main joint inside it
        v = person.vertices
        assert v[:, 1].min() == pytest.approx(0.0, abs=1e-6) and 0.4 < v[:, 1].max() < 2.6
    again = build_person(1, split, 1.0)
    np.testing.assert_array_equal(again.vertices, mixed[1].vertices)
    assert not np.array_equal(build_person(1, split).vertices, mixed[1].vertices)


def test_a_mirrored_pose_mirrored_again_is_the_pose(base):
    from export.factory.person import base_model, mirrored_pose, pose_rotations

    names = base_model().skeleton.names
    pose = pose_rotations("fight01", base_model().skeleton)
    np.testing.assert_allclose(mirrored_pose(mirrored_pose(pose, names), names), pose, atol=1e-12)
    once = mirrored_pose(pose, names)
    left, right = names.index("upperarm01.L"), names.index("upperarm01.R")
    # the left arm's turn is the right arm's, seen in a mirror: the same angle
    angle = lambda r: np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))  # noqa: E731
    assert angle(once[left]) == pytest.approx(angle(pose[right]))


def test_a_pose_read_once_is_handed_out_fresh(base):
    from export.factory.person import base_model, pose_rotations

    skeleton = base_model().skeleton
    first = pose_rotations("fight01", skeleton)
    first[:] = 0.0  # a caller may change its copy
    np.testing.assert_allclose(np.linalg.det(pose_rotations("fight01", skeleton)), 1.0, atol=1e-9)
    np.testing.assert_array_equal(pose_rotations("rest", skeleton)[3], np.eye(3))


def test_a_leg_keeps_its_turn_against_the_hips_of_its_own_pose(base):
    """gym01 is a handstand whose root turns the body half over and whose spine and pelvis turn
    it back: a leg taken into a standing pose hangs down from the hips, not up."""
    from export.factory.person import base_model, mixed_pose, pose_rotations

    skeleton = base_model().skeleton
    names = skeleton.names
    standing = pose_rotations("standing01", skeleton)

    class Donor:  # an rng that swaps the left leg alone in from gym01, unmirrored
        draws = iter([0.9, 0.9, 0.9, 0.0, 0.9, 0.9])  # trunk, arm.L, arm.R, leg.L (mirror? no), leg.R

        def random(self):
            return next(self.draws)

        def choice(self, poses):
            return "gym01"

    donor = Donor()
    out, mix = mixed_pose(standing, "train", skeleton, donor, 0.5)
    assert mix == {"leg.L": "gym01"}

    def world(rotations, bone):  # the bone's turn in the mesh frame: its parents' and its own
        turn, k = np.eye(3), names.index(bone)
        chain = []
        while k >= 0:
            chain.append(k)
            k = skeleton.parents[k]
        for k in reversed(chain):
            turn = turn @ rotations[k]
        return turn

    hips = lambda rotations: world(rotations, "spine05")  # noqa: E731
    handstand = pose_rotations("gym01", skeleton)
    # relative to the hips the thigh is turned as in the handstand
    np.testing.assert_allclose(hips(out).T @ world(out, "upperleg01.L"),
                               hips(handstand).T @ world(handstand, "upperleg01.L"), atol=1e-9)
