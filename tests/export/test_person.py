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
