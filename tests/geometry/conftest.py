"""Shared fixtures for the body-geometry tests: ground-truth maps rendered with embreex."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import geometry_truth  # noqa: E402


@pytest.fixture(scope="session")
def body_mesh():
    mesh = geometry_truth.makehuman_body()
    if mesh is None:
        pytest.skip(f"MakeHuman data not found at {geometry_truth.BODY_OBJ}")
    return mesh


@pytest.fixture(scope="session")
def body_maps(body_mesh):
    """The MakeHuman body seen by a 192x192 crop."""
    return geometry_truth.render_maps(body_mesh, geometry_truth.square_rect(body_mesh), 192, 192)


@pytest.fixture(scope="session")
def arm_maps():
    mesh = geometry_truth.arm_over_torso()
    return geometry_truth.render_maps(mesh, geometry_truth.square_rect(mesh), 96, 96)
