"""Fixtures shared across the test packages."""

import numpy as np
import pytest


@pytest.fixture
def stand_in_normals(monkeypatch):
    """The stand-in nets' normals kept as the stages' normals. Tests that check shading, albedo
    or the data factory's plumbing on known geometry (a slab, a ball in a slab, a sample's true
    maps) use it: those outlines are no body's, or the normals already exact, and the
    smoothing inside the person and the pull toward the outline's normals
    (relightcli.geometry.smoothing, relightcli.geometry.silhouette) are tested apart."""
    from relightcli.geometry import silhouette, smoothing

    monkeypatch.setattr(smoothing, "smooth_normals",
                        lambda normals, mask, sigma: np.asarray(normals, np.float32))
    monkeypatch.setattr(silhouette, "blend_silhouette_normals",
                        lambda normals, inside, outside_photo=None: np.asarray(normals, np.float32))
