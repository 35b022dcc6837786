"""Helpers for the render tests (plain functions, imported by name: a module called conftest
would clash with the other test folders' conftest.py when the whole suite runs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
HDRI = DATA / "hdri"
BODY_OBJ = DATA / "makehuman" / "base.obj"


def read_obj_group(path: Path, group: str = "body"):
    """Vertices (V, 3) float64 and triangles (F, 3) int64 of one `g` group of an OBJ file
    (polygons fan-triangulated, unused vertices dropped)."""
    vertices, faces, current = [], [], None
    with open(path) as handle:
        for line in handle:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                current = line.split(maxsplit=1)[1].strip()
            elif line.startswith("f ") and current == group:
                idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
                faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
    vertices, faces = np.asarray(vertices), np.asarray(faces, dtype=np.int64)
    used, inverse = np.unique(faces, return_inverse=True)
    return vertices[used], inverse.reshape(faces.shape)


def body_mesh():
    """The MakeHuman base body as a trimesh.Trimesh (skips the test if the data is missing)."""
    import trimesh

    if not BODY_OBJ.exists():
        pytest.skip(f"missing {BODY_OBJ}")
    vertices, faces = read_obj_group(BODY_OBJ)
    return trimesh.Trimesh(vertices, faces, process=False)


def load_hdr(name: str) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of a map in ../shared/data/hdri (skips if missing)."""
    import OpenImageIO as oiio

    path = HDRI / name
    if not path.exists():
        pytest.skip(f"missing {path}")
    image = oiio.ImageInput.open(str(path))
    pixels = image.read_image(format="float")
    image.close()
    return np.ascontiguousarray(pixels[..., :3], dtype=np.float32)


def quad(x0, x1, y0, y1, z):
    """Two triangles of the axis-aligned square [x0,x1]x[y0,y1] at height z, facing +Z."""
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]])


def merge(*parts):
    """Concatenate (vertices, faces) pairs into one mesh."""
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(np.asarray(f) + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def one_hot_map(height, row, col, value):
    """(H, 2H, 3) float32 map, zero but one texel."""
    env = np.zeros((height, 2 * height, 3), np.float32)
    env[row, col] = value
    return env


def chi_square_pvalue(observed, expected):
    """Chi-square p-value, cells with expected < 5 merged into one (pbrt's practice)."""
    from scipy import stats

    observed, expected = np.ravel(observed).astype(float), np.ravel(expected).astype(float)
    small = expected < 5
    obs = np.append(observed[~small], observed[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    keep = exp > 0
    if np.any(obs[~keep] > 0):
        return 0.0
    if keep.sum() == 1:  # one possible cell: the test is that nothing fell elsewhere
        return 1.0
    return stats.chisquare(obs[keep], exp[keep] * obs[keep].sum() / exp[keep].sum()).pvalue


def floor_under_a_square(resolution=96):
    """A floor and a square floating above it, seen from above: (Scene, its PixelGeometry)."""
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.scene import Scene

    scene = Scene(*merge(quad(-4.0, 4.0, -4.0, 4.0, 0.0), quad(-0.5, 0.5, -0.5, 0.5, 1.0)))
    return scene, render_pixel_geometry(scene, (-4.0, 4.0, -4.0, 4.0), (resolution, resolution))
