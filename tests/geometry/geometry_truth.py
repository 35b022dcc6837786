"""Ground truth for the geometry tests and bench: closed meshes (sphere, two capsules for an arm
in front of a torso, the MakeHuman body) rendered by our own embreex ray casts into the maps a
geometry net predicts (mask, front/back depth, front/back normals), DESIGN.md camera."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
BODY_OBJ = DATA / "makehuman" / "base.obj"


@dataclass
class Maps:
    """(H, W) bool mask; (H, W) float64 front/back depth (world z, 0 off the mask);
    (H, W, 3) float64 unit outward front/back normals; rect (x0, x1, y0, y1)."""

    mask: np.ndarray
    front_depth: np.ndarray
    back_depth: np.ndarray
    front_normal: np.ndarray
    back_normal: np.ndarray
    rect: tuple


def pixel_centres(rect, height, width):
    """(H, W) x and (H, W) y of the pixel centres (DESIGN.md formula, written out here)."""
    x0, x1, y0, y1 = rect
    x = x0 + (np.arange(width) + 0.5) * (x1 - x0) / width
    y = y1 - (np.arange(height) + 0.5) * (y1 - y0) / height
    return np.meshgrid(x, y)


def first_hits(mesh, origins, directions):
    """(N,) hit distance (inf on a miss) and (N, 3) unit face normal of the hit (winding)."""
    from embreex import mesh_construction, rtcore_scene

    scene = rtcore_scene.EmbreeScene()
    centre = mesh.bounds.mean(axis=0)
    vertices = np.ascontiguousarray(mesh.vertices - centre, dtype=np.float32)
    mesh_construction.TriangleMesh(scene, vertices, np.ascontiguousarray(mesh.faces, np.int32))
    out = scene.run(np.ascontiguousarray(origins - centre, np.float32),
                    np.ascontiguousarray(directions, np.float32), output=1)
    hit = out["primID"] >= 0
    t = np.where(hit, out["tfar"].astype(np.float64), np.inf)
    normals = np.zeros((origins.shape[0], 3))
    normals[hit] = mesh.face_normals[out["primID"][hit]]
    return t, normals


def render_maps(mesh, rect, height, width) -> Maps:
    """First hit along -Z (front) and along +Z from behind (back) through every pixel centre."""
    x, y = pixel_centres(rect, height, width)
    lo, hi = mesh.bounds[0, 2] - 1.0, mesh.bounds[1, 2] + 1.0
    n = x.size
    xy = np.column_stack([x.ravel(), y.ravel()])
    t_front, n_front = first_hits(mesh, np.column_stack([xy, np.full(n, hi)]),
                                  np.tile([0.0, 0.0, -1.0], (n, 1)))
    t_back, n_back = first_hits(mesh, np.column_stack([xy, np.full(n, lo)]),
                                np.tile([0.0, 0.0, 1.0], (n, 1)))
    mask = np.isfinite(t_front) & np.isfinite(t_back)
    front = np.where(mask, hi - np.where(mask, t_front, 0.0), 0.0)
    back = np.where(mask, lo + np.where(mask, t_back, 0.0), 0.0)
    shape = (height, width)
    return Maps(mask.reshape(shape), front.reshape(shape), back.reshape(shape),
                (n_front * mask[:, None]).reshape(shape + (3,)),
                (n_back * mask[:, None]).reshape(shape + (3,)), tuple(rect))


def square_rect(mesh, pad=0.05):
    """A square world rectangle around the mesh's x/y bounds, padded."""
    lo, hi = mesh.bounds[0, :2], mesh.bounds[1, :2]
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2 * (1 + pad)
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)


def sphere(radius=1.0):
    return trimesh.creation.icosphere(subdivisions=5, radius=radius)


def arm_over_torso():
    """A torso capsule (radius 0.5) and a thinner arm capsule (radius 0.15) crossing in front
    of it, overlapping it: a depth jump inside the silhouette."""
    torso = trimesh.creation.capsule(height=1.2, radius=0.5, count=[48, 48])
    arm = trimesh.creation.capsule(height=1.6, radius=0.15, count=[32, 32])
    arm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    arm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 3, [0, 0, 1]))
    arm.apply_translation([0.0, 0.0, 0.55])
    torso.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return trimesh.util.concatenate([torso, arm])


def makehuman_body():
    """The MakeHuman base mesh, `g body` faces only, as a trimesh (None if the data is absent)."""
    if not BODY_OBJ.exists():
        return None
    vertices, faces, group = [], [], None
    with open(BODY_OBJ) as handle:
        for line in handle:
            if line.startswith("v "):
                vertices.append([float(v) for v in line.split()[1:4]])
            elif line.startswith("g "):
                group = line.split(maxsplit=1)[1].strip()
            elif line.startswith("f ") and group == "body":
                corners = [int(token.split("/")[0]) - 1 for token in line.split()[1:]]
                faces += [[corners[0], corners[k], corners[k + 1]]
                          for k in range(1, len(corners) - 1)]
    return trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=True)
