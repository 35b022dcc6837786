"""Macro-target weighting and random bodies."""

import numpy as np
import pytest

from export.factory import shape
from export.factory.person import sample_body


@pytest.mark.parametrize("value", [0.0, 0.1, 0.1875, 0.3, 0.5, 0.77, 1.0])
def test_age_knot_weights_sum_to_one(value):
    weights = shape.knot_weights(value, shape.AGE_KNOTS)
    assert sum(weights.values()) == pytest.approx(1.0)
    assert len(weights) <= 2


def test_knot_weights_interpolate_linearly():
    assert shape.knot_weights(0.75, shape.AGE_KNOTS) == pytest.approx({"young": 0.5, "old": 0.5})


@pytest.mark.parametrize("family", ["-young.target", "universal-", "height/", "proportions/"])
def test_macro_families_have_the_expected_total_weight(family):
    params = shape.ShapeParams(gender=0.3, age=0.7, muscle=0.6, weight=0.2, height=0.8,
                               proportions=0.9, race=(0.2, 0.3, 0.5))
    weights = shape.macro_target_weights(params)
    total = sum(w for name, w in weights.items() if family in name or
                (family == "-young.target" and name.endswith("-old.target")))
    expected = {"-young.target": 1.0, "universal-": 1.0, "height/": 0.6, "proportions/": 0.8}
    assert total == pytest.approx(expected[family])


def test_every_weighted_macro_file_exists(makehuman_data):
    rng = np.random.default_rng(0)
    params = shape.sample_shape(rng)
    from export.factory import assets

    missing = [n for n in shape.all_target_weights(params)
               if not (assets.core_path("targets") / n).is_file()]
    assert missing == []


@pytest.fixture(scope="module", params=[0, 1, 2])
def random_body(request, base):
    params, shaped = sample_body(np.random.default_rng(request.param), base)
    return params, shaped


def test_random_body_has_plausible_height(random_body, base):
    _, shaped = random_body
    body = np.unique(base.mesh.faces[base.body_faces])
    assert 1.4 < shape.stature(shaped, body) < 2.1


def test_random_body_moves_no_vertex_beyond_target_magnitudes(random_body, base):
    params, shaped = random_body
    bound = shape.max_displacement_bound(shape.all_target_weights(params))
    bound = np.pad(bound, (0, len(shaped) - bound.size))
    moved = np.linalg.norm(shaped - base.mesh.vertices, axis=1)
    assert np.all(moved <= bound + 1e-9)
    assert moved.max() < 0.5  # metres: no exploded vertex on an adult body


def test_random_body_has_no_stretched_edges(random_body, base):
    _, shaped = random_body
    faces = base.mesh.faces[base.body_faces]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    rest = np.linalg.norm(np.diff(base.mesh.vertices[edges], axis=1)[:, 0], axis=1)
    now = np.linalg.norm(np.diff(shaped[edges], axis=1)[:, 0], axis=1)
    # The base mesh's longest body edge is 6.5 cm; an exploded vertex would add decimetres.
    assert now.max() < 0.12
    assert (now - rest).max() < 0.05


def test_solved_height_reaches_the_requested_stature(base):
    params = shape.sample_shape(np.random.default_rng(5))
    body = np.unique(base.mesh.faces[base.body_faces])
    h = shape.solve_height_param(params, base.mesh.vertices, body, 1.70)
    solved = shape.ShapeParams(**{**params.as_dict(), "height": h, "race": params.race,
                                  "details": params.details})
    shaped = shape.apply_targets(base.mesh.vertices, shape.all_target_weights(solved))
    got = shape.stature(shaped, body)
    assert got == pytest.approx(1.70, abs=0.02)
