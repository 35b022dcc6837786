"""Double-sided depth maps -> a closed, watertight mesh pixel-aligned with the crop.

The camera is DESIGN.md's orthographic one: it looks along -Z, +Z toward the viewer, and pixel
(i, j) of an H x W crop over the world rectangle [x0, x1] x [y0, y1] has its centre at
x = x0 + (j + 0.5)(x1 - x0)/W, y = y1 - (i + 0.5)(y1 - y0)/H.

Construction (all vectorised):
1. One vertex per mask pixel, at its centre, with the front depth as z: the mesh's front
   surface passes exactly through (x_j, y_i, front_depth[i, j]).
2. Every 2x2 block of pixel centres with 4 pixels in the mask gives two triangles (split along
   the diagonal with the smaller depth step), one with 3 gives one triangle. The result is a
   planar, consistently wound triangulation of the mask's interior.
3. Vertices where two triangle fans touch only at a point (two blocks meeting diagonally) are
   split into one vertex per fan, so every boundary vertex lies on exactly one boundary loop.
4. The back surface is the same triangulation at the back depth with reversed winding; a strip
   of two triangles per boundary edge joins front and back along the silhouette.

Mask structures thinner than two pixels (one-pixel limbs, isolated pixels) belong to no 2x2
block with 3 pixels and are left out: the mesh covers the mask's triangulable part, returned
by `covered_pixels`.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from typing import NamedTuple

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from relightcli.errors import InputError, OutputError, UsageError
from relightcli.render.camera import pixel_centres

MESH_FORMATS = {".ply": "ply", ".glb": "glb", ".obj": "obj"}


class TriangleMesh(NamedTuple):
    """A mesh as arrays: (V, 3) float64 vertices, (F, 3) int faces. The pipeline keeps its
    meshes so; `to_trimesh()` makes a trimesh.Trimesh (process=False) for a mesh file or the
    Python API: trimesh and the networkx it pulls in take ~0.25 s to import, so only the runs
    that hand a mesh out load them."""

    vertices: np.ndarray
    faces: np.ndarray

    def to_trimesh(self):
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, process=False)


def reconstruct_mesh(mask, front_depth, back_depth, rect, *, min_thickness: float = 0.0,
                     mask_threshold: float = 0.5) -> TriangleMesh:
    """Closed mesh of the person from front and back depth maps.

    mask: (H, W) bool or float in [0, 1] (pixels > mask_threshold are inside).
    front_depth, back_depth: (H, W) float, world z of the nearest and farthest surface along
    the pixel's ray (front = larger z), finite on the mask. rect: (x0, x1, y0, y1) world
    rectangle the crop covers. min_thickness: world units; the back depth is clamped to at most
    front - min_thickness (a back surface in front of the front one is not a surface).
    Returns a TriangleMesh (float64 vertices in the crop's camera/world frame, outward
    winding, watertight; `to_trimesh()` merges no vertex).
    Raises InputError for mismatched shapes, non-finite depths on the mask, or a mask with no
    2x2 block of pixels.
    """
    inside = _check_maps(mask, front_depth, back_depth, mask_threshold)
    front = np.asarray(front_depth, dtype=np.float64)
    back = np.minimum(np.asarray(back_depth, dtype=np.float64), front - float(min_thickness))
    height, width = inside.shape
    faces = _grid_triangles(inside, front)
    if faces.shape[0] == 0:
        raise InputError("the mask has no 2x2 block of pixels to build a surface from",
                         fix="pass a mask of the whole person (at least 2 pixels wide)")
    boundary = _boundary_half_edges(faces, width)
    faces, pixel = _split_pinched_vertices(faces, boundary, height * width)
    faces, pixel = _drop_unused_vertices(faces, pixel)
    xy = pixel_centres(rect, (width, height)).reshape(-1, 2)[pixel]
    vertices = np.concatenate([np.column_stack([xy, front.ravel()[pixel]]),
                               np.column_stack([xy, back.ravel()[pixel]])])
    n = pixel.size
    side = _side_strip(_half_edges(faces)[boundary], n)
    all_faces = np.concatenate([faces, faces[:, ::-1] + n, side])
    return TriangleMesh(vertices, all_faces)


def covered_pixels(mask, *, mask_threshold: float = 0.5) -> np.ndarray:
    """(H, W) bool: mask pixels that are a corner of some mesh triangle (the pixels whose
    centre lies on the reconstructed front surface)."""
    inside = np.asarray(mask) > mask_threshold
    blocks = (inside[:-1, :-1].astype(np.int8) + inside[:-1, 1:] + inside[1:, :-1]
              + inside[1:, 1:]) >= 3
    covered = np.zeros_like(inside)
    for di in (0, 1):
        for dj in (0, 1):
            covered[di:di + blocks.shape[0], dj:dj + blocks.shape[1]] |= blocks
    return covered & inside


def save_mesh(mesh, path) -> Path:
    """Write a mesh (a TriangleMesh or a trimesh.Trimesh) as .ply, .glb or .obj, atomically: a
    temporary file in the same folder, then os.replace, so a reader never sees a half-written
    file. Returns the path. Raises UsageError for another suffix, OutputError when the folder
    cannot be written."""
    path = Path(path)
    file_type = MESH_FORMATS.get(path.suffix.lower())
    if file_type is None:
        raise UsageError(f"cannot write a mesh as '{path.suffix}'", path=path,
                         fix="use a .ply, .glb or .obj file name")
    if isinstance(mesh, TriangleMesh):
        mesh = mesh.to_trimesh()
    data = mesh.export(file_type=file_type)
    data = data.encode("utf-8") if isinstance(data, str) else data
    try:
        handle, temporary = _create_temporary(path)
    except OSError as error:
        raise OutputError(f"cannot write the mesh: {error.strerror}", path=path,
                          fix="choose a folder that exists and is writable") from error
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(data)
        os.replace(temporary, path)
    except OSError as error:
        Path(temporary).unlink(missing_ok=True)
        raise OutputError(f"cannot write the mesh: {error.strerror}", path=path,
                          fix="check free space and permissions") from error
    return path


# ---------------------------------------------------------------------------- internals

def _create_temporary(path: Path) -> tuple[int, str]:
    """(open descriptor, name) of a new empty file beside `path`. Mode 0o666 under the umask,
    as the images get (io.images._temporary_path); mkstemp's 0o600 would leave the mesh
    unreadable to everyone else."""
    while True:
        temporary = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
        try:
            return os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), str(temporary)
        except FileExistsError:
            continue


def _check_maps(mask, front_depth, back_depth, mask_threshold):
    """The inside mask (H, W) bool, after checking shapes and finiteness."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or min(mask.shape) < 2:
        raise InputError(f"mask must be an (H, W) array with H, W >= 2, got shape {mask.shape}")
    for name, depth in (("front depth", front_depth), ("back depth", back_depth)):
        if np.shape(depth) != mask.shape:
            raise InputError(f"{name} has shape {np.shape(depth)}, the mask {mask.shape}",
                             fix="pass maps of the same crop")
    inside = mask > mask_threshold
    for name, depth in (("front depth", front_depth), ("back depth", back_depth)):
        bad = np.count_nonzero(~np.isfinite(np.asarray(depth, dtype=np.float64)[inside]))
        if bad:
            raise InputError(f"{name} has {bad} NaN or Inf values inside the mask",
                             fix="fill or mask out those pixels")
    return inside


def _grid_triangles(inside, depth):
    """(F, 3) int64 triangles over 2x2 blocks of pixel centres, as flat pixel indices
    i * W + j, counter-clockwise seen from +Z.

    Corners of a block: a = top-left, b = top-right, c = bottom-left, d = bottom-right.
    Row i grows downward (y decreases), so a -> c -> d -> b is counter-clockwise from +Z.
    """
    height, width = inside.shape
    flat = np.arange(height * width).reshape(height, width)
    a, b, c, d = flat[:-1, :-1], flat[:-1, 1:], flat[1:, :-1], flat[1:, 1:]
    ia, ib = inside[:-1, :-1], inside[:-1, 1:]
    ic, id_ = inside[1:, :-1], inside[1:, 1:]
    full = ia & ib & ic & id_
    # Split a full block along the diagonal with the smaller depth step (follows creases)
    along_bc = full & (np.abs(depth[:-1, 1:] - depth[1:, :-1])
                       < np.abs(depth[:-1, :-1] - depth[1:, 1:]))
    along_ad = full & ~along_bc
    pieces = [
        (along_ad, (a, c, d)), (along_ad, (a, d, b)),
        (along_bc, (a, c, b)), (along_bc, (c, d, b)),
        (~ia & ib & ic & id_, (c, d, b)), (ia & ~ib & ic & id_, (a, c, d)),
        (ia & ib & ~ic & id_, (a, d, b)), (ia & ib & ic & ~id_, (a, c, b)),
    ]
    return np.concatenate(
        [np.column_stack([k[where] for k in corners]) for where, corners in pieces])


def _half_edges(faces):
    """(3F, 2) int64: half-edge 3 f + k runs faces[f, k] -> faces[f, (k + 1) % 3]."""
    return np.column_stack([faces.ravel(), np.roll(faces, -1, axis=1).ravel()])


def _boundary_half_edges(faces, width):
    """(3F,) bool: half-edges of grid triangles (flat pixel indices) that no other triangle
    shares. A grid edge joins p < q with q - p in {1, W - 1, W, W + 1}, so (p, q - p) names it
    and a bincount finds the edges used once, without sorting."""
    edges = _half_edges(faces)
    low, high = edges.min(axis=1), edges.max(axis=1)
    code = np.searchsorted(np.array([1, width - 1, width, width + 1]), high - low)
    key = 4 * low + code
    return np.bincount(key)[key] == 1


def _split_pinched_vertices(faces, boundary, n_pixels):
    """Give each triangle fan around a vertex its own vertex.

    A vertex whose triangles form two fans touching only at it (two blocks meeting at a
    corner) sits on two boundary loops; the side strip would then put four faces on one edge.
    Such a vertex starts two boundary half-edges. Around it, triangle corners are joined across
    shared edges; each connected group becomes a new vertex (index >= n_pixels).
    Returns (faces (F, 3) int64, pixel (V,) int64: the pixel of each vertex index).
    """
    edges = _half_edges(faces)
    starts = np.bincount(edges[boundary, 0], minlength=n_pixels)
    pixel = np.arange(n_pixels)
    pinched = starts > 1
    if not pinched.any():
        return faces, pixel
    # Half-edges of triangles around pinched vertices, matched with their twins by sorting
    near = np.flatnonzero(np.repeat(pinched[faces].any(axis=1), 3))
    key = edges[near, 0] * n_pixels + edges[near, 1]
    twin_key = edges[near, 1] * n_pixels + edges[near, 0]
    order = np.argsort(key)
    slot = np.minimum(np.searchsorted(key[order], twin_key), key.size - 1)
    matched = key[order][slot] == twin_key
    edge, twin = near[matched], near[order[slot[matched]]]
    # Half-edge e runs corner e -> corner next(e), its twin next(t) -> t: corner e and corner
    # next(t) see the same vertex, so do next(e) and t
    next_e = edge - edge % 3 + (edge % 3 + 1) % 3
    next_t = twin - twin % 3 + (twin % 3 + 1) % 3
    rows, cols = np.concatenate([edge, next_e]), np.concatenate([next_t, twin])
    keep = pinched[faces.ravel()[rows]]
    graph = scipy.sparse.coo_matrix(
        (np.ones(np.count_nonzero(keep), np.int8), (rows[keep], cols[keep])),
        shape=(faces.size, faces.size))
    corners = np.flatnonzero(pinched[faces.ravel()])
    _, group = scipy.sparse.csgraph.connected_components(graph, directed=False)
    _, group = np.unique(group[corners], return_inverse=True)
    split = faces.ravel().copy()
    split[corners] = n_pixels + group
    extra = np.empty(group.max() + 1, dtype=np.int64)
    extra[group] = faces.ravel()[corners]
    return split.reshape(faces.shape), np.concatenate([pixel, extra])


def _drop_unused_vertices(faces, pixel):
    """Renumber vertices 0..V-1 in order, keeping only those some face uses."""
    used = np.zeros(pixel.size, dtype=bool)
    used[faces] = True
    renumber = np.cumsum(used) - 1
    return renumber[faces], pixel[used]


def _side_strip(edges, n):
    """(2B, 3) triangles joining front boundary edge a -> b to its back copy (a+n, b+n).

    The strip runs each edge the other way (b -> a) at the front, a+n -> b+n at the back
    (whose triangles are reversed), so every edge is shared by exactly two faces."""
    a, b = edges[:, 0], edges[:, 1]
    return np.concatenate([np.column_stack([b, a, a + n]), np.column_stack([b, a + n, b + n])])
