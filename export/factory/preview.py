"""Quick look at built people: an orthographic Embree z-buffer render with textured albedo and
simple Lambert + ambient shading, for contact sheets only (not the project integrator).

Run `python -m export.factory.preview OUT.png [seed ...]` to write a sheet.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from relightcli.io.images import write_image

from .albedo import sample_texture
from .person import Person, build_person

LIGHT = np.array([0.4, 0.6, 0.7]) / np.linalg.norm([0.4, 0.6, 0.7])


def render_person(person: Person, height_px: int = 384, width_px: int = 256,
                  yaw_degrees: float = 0.0) -> np.ndarray:
    """Orthographic front view (camera along -Z) of a person turned by `yaw_degrees` about +Y.

    Returns (height_px, width_px, 3) float32 linear RGB, white background; the frame covers
    2.2 m x 2.2 * width/height m, feet 0.1 m above the bottom edge.
    """
    c, s = np.cos(np.radians(yaw_degrees)), np.sin(np.radians(yaw_degrees))
    verts = person.vertices @ np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=np.float32).T
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, verts[person.faces].astype(np.float32))
    extent_y = 2.2
    extent_x = extent_y * width_px / height_px
    cols = (np.arange(width_px) + 0.5) / width_px * extent_x - extent_x / 2
    rows = extent_y - 0.1 - (np.arange(height_px) + 0.5) / height_px * extent_y
    x, y = np.meshgrid(cols, rows)
    origins = np.stack([x.ravel(), y.ravel(), np.full(x.size, 10.0)], axis=1).astype(np.float32)
    dirs = np.tile(np.array([0, 0, -1], dtype=np.float32), (x.size, 1))
    hit = scene.run(origins, dirs, output=1)
    image = np.ones((x.size, 3), dtype=np.float32)
    ok = hit["primID"] >= 0
    prim, u, v = hit["primID"][ok], hit["u"][ok], hit["v"][ok]
    bary = np.stack([1 - u - v, u, v], axis=1)
    uv = np.einsum("nk,nkd->nd", bary, person.face_uv[prim])
    normal = hit["Ng"][ok] / np.linalg.norm(hit["Ng"][ok], axis=1, keepdims=True)
    normal *= np.sign(normal[:, 2:3] + 1e-9)  # face the camera (both-sided preview)
    shade = 0.25 + 0.75 * np.clip(normal @ LIGHT, 0, None)
    image[ok] = sample_texture(person.texture, uv) * shade[:, None]
    return image.reshape(height_px, width_px, 3)


def contact_sheet(seeds: list[int], split: str = "train", columns: int = 6) -> np.ndarray:
    """Front and 60-degree views of each seed, `columns` views per row: (H rows, W columns, 3)
    float32 linear (a short last row is padded with white)."""
    tiles = []
    for seed in seeds:
        person = build_person(seed, split)
        tiles += [render_person(person), render_person(person, yaw_degrees=60.0)]
    tiles += [np.ones_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[k:k + columns], axis=1) for k in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)


def main(argv: list[str]) -> None:
    out = Path(argv[0])
    seeds = [int(a) for a in argv[1:]] or list(range(9))
    sheet = contact_sheet(seeds)
    write_image(out, sheet)


if __name__ == "__main__":
    main(sys.argv[1:])
