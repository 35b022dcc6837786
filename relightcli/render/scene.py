"""Triangle meshes on Embree (embreex): construction, ray offsets, parallel tracing.

Coordinates are re-centred in float64 (the bounding-box centre is subtracted) before the cast
to float32, so a mesh translated by 1e5 traces like the same mesh at the origin. Every
position the scene takes or returns is in this local frame: `to_local` / `to_world` convert.
Ray origins are offset along the geometric normal by `ray_offset`, a fixed fraction of the
bounding-box diagonal, so scenes from 1e-3 to 1e4 units behave alike.

`threads > 1` traces on worker processes that each hold their own copy of the BVH; the calling
process traces one share itself. `parallel="thread"` keeps a thread pool instead: embreex 4.4
releases the GIL while it traces (two threads trace 2 million rays 1.8-2x faster than one;
the processes date from a version that held it), which the pipeline's two lines of stages
rely on (pipeline.SideLine).
"""

from __future__ import annotations

import functools
import multiprocessing
import weakref
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from relightcli.errors import InputError

# Ray-origin offset as a fraction of the bounding-box diagonal: ~1e3 float32 ulps of the
# largest local coordinate, far above Embree's intersection error, far below any feature.
RAY_OFFSET_FRACTION = 1e-5
# Below this many rays a batch is traced in the calling process only.
MIN_PARALLEL_RAYS = 8192
_FAR = np.float32(1e30)


@dataclass
class Hits:
    """Closest hits of N rays. prim (N,) int32, -1 for a miss; t (N,) float32 distance;
    bary (N, 2) float32 Embree barycentrics (b1, b2), the hit is b0 p0 + b1 p1 + b2 p2;
    geometric_normal (N, 3) float32, unit, right-handed from the winding (not flipped toward
    the ray), zero for misses."""

    prim: np.ndarray
    t: np.ndarray
    bary: np.ndarray
    geometric_normal: np.ndarray

    @property
    def hit(self):
        return self.prim >= 0


def _build_embree(vertices, faces):
    from embreex import mesh_construction, rtcore_scene

    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, vertices, faces)
    return scene


def _trace(embree_scene, origins, directions, tmax, intersect):
    """One embreex call. Returns Hits for intersect, else occluded (N,) bool."""
    if intersect:
        out = embree_scene.run(origins, directions, dists=tmax, query="INTERSECT", output=1)
        return out["primID"], out["tfar"], np.stack([out["u"], out["v"]], axis=1), out["Ng"]
    return embree_scene.run(origins, directions, dists=tmax, query="OCCLUDED") >= 0


_WORKER_SCENE = None


def _worker_init(vertices, faces):
    global _WORKER_SCENE
    _WORKER_SCENE = _build_embree(vertices, faces)


def _worker_trace(origins, directions, tmax, intersect):
    return _trace(_WORKER_SCENE, origins, directions, tmax, intersect)


class Scene:
    """A triangle mesh ready for ray queries.

    vertices: (V, 3) float, world units; faces: (F, 3) int; vertex_normals: (V, 3) float or
    None (area-weighted normals are computed). smooth_normals=False shades with the geometric
    (face) normals instead. threads: how many processes (or threads) trace.
    """

    def __init__(self, vertices, faces, *, vertex_normals=None, smooth_normals: bool = True,
                 threads: int = 1, parallel: str = "process"):
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        _check_mesh(vertices, faces)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        self.centre = (lo + hi) / 2.0
        self.diagonal = float(np.linalg.norm(hi - lo))
        if not self.diagonal > 0:
            raise InputError("mesh has zero extent", fix="pass a mesh with non-degenerate triangles")
        self.ray_offset = RAY_OFFSET_FRACTION * self.diagonal
        self.vertices = np.ascontiguousarray(vertices - self.centre, dtype=np.float32)
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self.bounds_local = np.stack([lo - self.centre, hi - self.centre])
        self.face_normals = _face_normals(vertices, self.faces)
        self.vertex_normals = _vertex_normals(vertices, self.faces, vertex_normals)
        self.smooth_normals = bool(smooth_normals)
        self._embree = _build_embree(self.vertices, self.faces)
        self.threads = max(1, int(threads))
        self.parallel = parallel
        self.rays_traced = 0
        self._pool = None
        self._finalizer = None

    @classmethod
    def from_trimesh(cls, mesh, *, smooth_normals: bool = True, threads: int = 1,
                     parallel: str = "process") -> "Scene":
        """From a trimesh.Trimesh; its vertex normals become the shading normals."""
        return cls(mesh.vertices, mesh.faces, vertex_normals=mesh.vertex_normals,
                   smooth_normals=smooth_normals, threads=threads, parallel=parallel)

    @functools.cached_property
    def edge_length(self) -> float:
        """The median length of the triangles' edges: the scale by which shadow rays are lifted
        off them (relightcli.render.estimators.lifted_origins)."""
        corners = self.vertices[self.faces].astype(np.float64)
        return float(np.median(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)))

    # ------------------------------------------------------------ frames
    def to_local(self, points):
        """World points (..., 3) -> local float64 (subtract the centre in float64)."""
        return np.asarray(points, dtype=np.float64) - self.centre

    def to_world(self, points):
        """Local points (..., 3) -> world float64."""
        return np.asarray(points, dtype=np.float64) + self.centre

    # ------------------------------------------------------------ queries
    def intersect(self, origins, directions, tmax=None) -> Hits:
        """Closest hits for local origins (N, 3) and unit directions (N, 3)."""
        parts = self._run(origins, directions, tmax, intersect=True)
        prim = np.concatenate([p[0] for p in parts])
        ng = np.where((prim >= 0)[:, None], self.face_normals[np.maximum(prim, 0)], 0.0)
        return Hits(prim=prim, t=np.concatenate([p[1] for p in parts]),
                    bary=np.concatenate([p[2] for p in parts]), geometric_normal=ng)

    def occluded(self, origins, directions, tmax=None) -> np.ndarray:
        """(N,) bool: does the segment origin + t dir, 0 < t < tmax, hit anything."""
        return np.concatenate(self._run(origins, directions, tmax, intersect=False))

    def shading_normals(self, hits: Hits) -> np.ndarray:
        """Interpolated vertex normals (N, 3) float32 at hits (unit; zero rows for misses);
        the geometric normals when the scene is not smooth."""
        if not self.smooth_normals:
            return hits.geometric_normal.astype(np.float32)
        prim = np.where(hits.hit, hits.prim, 0)
        corners = self.vertex_normals[self.faces[prim]]  # (N, 3, 3)
        b1, b2 = hits.bary[:, 0:1], hits.bary[:, 1:2]
        n = (1.0 - b1 - b2) * corners[:, 0] + b1 * corners[:, 1] + b2 * corners[:, 2]
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where(length > 0, n / np.where(length > 0, length, 1.0), hits.geometric_normal)
        return np.where(hits.hit[:, None], n, 0.0).astype(np.float32)

    def _run(self, origins, directions, tmax, intersect):
        origins = np.ascontiguousarray(origins, dtype=np.float32)
        directions = np.ascontiguousarray(directions, dtype=np.float32)
        n = origins.shape[0]
        tmax = np.full(n, _FAR, np.float32) if tmax is None else np.ascontiguousarray(
            np.broadcast_to(np.asarray(tmax, dtype=np.float32), (n,)))
        self.rays_traced += n
        if self.threads == 1 or n < MIN_PARALLEL_RAYS:
            return [_trace(self._embree, origins, directions, tmax.copy(), intersect)]
        bounds = np.linspace(0, n, self.threads + 1).astype(np.int64)
        chunks = [(origins[a:b], directions[a:b], tmax[a:b].copy(), intersect)
                  for a, b in zip(bounds[:-1], bounds[1:])]
        pool = self._executor()
        if self.parallel == "thread":
            futures = [pool.submit(_trace, self._embree, *c) for c in chunks]
            return [f.result() for f in futures]
        futures = [pool.submit(_worker_trace, *c) for c in chunks[1:]]
        own = _trace(self._embree, *chunks[0])
        return [own] + [f.result() for f in futures]

    def _executor(self):
        if self._pool is None:
            if self.parallel == "thread":
                self._pool = ThreadPoolExecutor(self.threads)
            elif self.parallel == "process":
                self._pool = ProcessPoolExecutor(
                    self.threads - 1, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_worker_init, initargs=(self.vertices, self.faces))
            else:
                raise ValueError(f"parallel must be 'process' or 'thread', got {self.parallel!r}")
            self._finalizer = weakref.finalize(self, self._pool.shutdown, wait=False, cancel_futures=True)
        return self._pool

    def commit(self):
        """Build the BVH now (embreex builds it lazily, on the first query)."""
        self._embree.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32),
                         query="OCCLUDED")

    def detach_workers(self):
        """Forget the tracing pool without stopping it (in a forked child, which must not use
        its parent's pool) and trace on this process alone."""
        self._pool, self._finalizer, self.threads = None, None, 1

    def warm_up(self):
        """Start the tracing workers now (a process pool takes ~0.5 s to start)."""
        if self.threads > 1:
            n = MIN_PARALLEL_RAYS * self.threads
            self.occluded(np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)))
            self.rays_traced -= n

    def close(self):
        """Stop the tracing workers."""
        if self._finalizer is not None:
            self._finalizer()
            self._pool = None
            self._finalizer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def orient_normals(geometric, shading, directions):
    """Normals at hits, facing the side the rays (N, 3) came from. geometric (N, 3) as the
    winding gives it, shading (N, 3) interpolated. Returns (shading, geometric) float64 (N, 3):
    both flipped where the ray hit the back side; the shading normal replaced by the
    geometric one where it still faces away from it."""
    geometric = np.asarray(geometric, dtype=np.float64)
    shading = np.asarray(shading, dtype=np.float64)
    sign = np.where(np.sum(geometric * directions, axis=1) > 0, -1.0, 1.0)[:, None]
    geometric, shading = geometric * sign, shading * sign
    shading = np.where((np.sum(shading * geometric, axis=1) > 0)[:, None], shading, geometric)
    return shading, geometric


def _check_mesh(vertices, faces):
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < 3:
        raise InputError(f"mesh vertices must be (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
        raise InputError(f"mesh faces must be (F, 3) triangles, got {faces.shape}",
                         fix="triangulate the mesh")
    if not np.all(np.isfinite(vertices)):
        raise InputError("mesh has NaN or Inf vertex coordinates", fix="repair the mesh")
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise InputError("mesh faces index vertices that do not exist", fix="repair the mesh")


def _face_normals(vertices, faces):
    """(F, 3) float32 unit normals, right-handed from the winding (zero for degenerate faces)."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0, length, 1.0)).astype(np.float32)


def corner_angle_normals(vertices, faces) -> np.ndarray:
    """(V, 3) float64 unit vertex normals: the faces' unit normals weighted by their corner's
    angle at the vertex (Thuerrner and Wuethrich 1998; trimesh's `vertex_normals`, which the
    face's shading used before). Faces without a normal (zero area) count nothing; a vertex of
    none gets zero."""
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.where(length > 0, normal / np.where(length > 0, length, 1.0), 0.0)
    angles = np.empty(faces.shape)
    for k in range(3):  # the angle at corner k between its two edges
        a, b = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
        a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300)
        b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
        angles[:, k] = np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0))
    weights = angles * (length > 0)
    summed = np.stack([np.bincount(faces.ravel(), weights=(weights * normal[:, [k]]).ravel(),
                                   minlength=len(vertices)) for k in range(3)], axis=1)
    total = np.linalg.norm(summed, axis=1, keepdims=True)
    return summed / np.where(total > 0, total, 1.0)


def _vertex_normals(vertices, faces, given):
    """(V, 3) float32 unit normals: the given ones, else area-weighted face normals."""
    if given is not None:
        normals = np.asarray(given, dtype=np.float64)
    else:
        tri = vertices[faces]
        face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 area
        # Each face's normal added to its three vertices (bincount: ~2x faster than np.add.at)
        corners = faces.ravel()
        normals = np.stack([np.bincount(corners, weights=np.repeat(face_n[:, k], 3), minlength=len(vertices))
                            for k in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return (normals / np.where(length > 0, length, 1.0)).astype(np.float32)
