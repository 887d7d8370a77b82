"""Receiver geometry for shading: vertex normals, receivers, view and mirror directions.

The points light arrives at (mesh vertices or texels, with unit normals and which of
them are defined), their directions towards the eye and the mirror directions Phong
lobes use, and the blocked dot products every culling and shading stage shares
(:func:`dot3`, so a pair's n·ω is bit-identical wherever it is computed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# OpenBLAS multithreads a GEMM above 4·65536 multiply-adds; stay below (see dot3).
GEMM_SINGLE = 1 << 17

def vertex_normals(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Unit vertex normals, repairing missing ones; which are defined.

    Given normals that are finite and non-zero are normalized and kept; the rest
    take the area-weighted mean of adjacent face normals (zero-area faces add
    nothing).  A vertex with no adjacent face of non-zero area has an undefined
    normal: it gets (0, 0, 0) and ``defined`` False, and all its features are 0.

    Args:
        vertices: [V, 3] float, metres, world.
        faces: [F, 3] int.
        normals: [V, 3] or None.

    Returns:
        normals [V, 3] float64 (unit or zero), defined [V] bool.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    n = len(vertices)
    out = np.zeros((n, 3))
    good = np.zeros(n, bool)
    if normals is not None:
        given = np.asarray(normals, np.float64).reshape(n, 3)
        with np.errstate(invalid="ignore", over="ignore"):
            length = np.linalg.norm(given, axis=1)
        good = np.isfinite(length) & (length > 1e-12)
        out[good] = given[good] / length[good, None]
    if not good.all() and len(faces):
        tri = vertices[faces]
        face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])   # area-weighted
        face_n[~np.isfinite(face_n).all(1)] = 0
        acc = np.zeros((n, 3))
        for k in range(3):
            np.add.at(acc, faces[:, k], face_n)
        length = np.linalg.norm(acc, axis=1)
        fix = ~good & (length > 1e-30)
        out[fix] = acc[fix] / length[fix, None]
        good = good | fix
    return out, good


@dataclass
class Receivers:
    """Points that receive light: positions, unit normals, and which normals are defined."""

    points: np.ndarray        # [N, 3] float64, metres, world
    normals: np.ndarray       # [N, 3] float64 unit (zero where undefined)
    defined: np.ndarray       # [N] bool

    def __len__(self):
        return len(self.points)


def scene_diagonal(meshes) -> float:
    """Bounding-box diagonal (metres) of a list of (vertices, faces)."""
    pts = [np.asarray(v, np.float64).reshape(-1, 3) for v, _ in meshes if len(v)]
    if not pts:
        return 1.0
    allp = np.concatenate(pts)
    allp = allp[np.isfinite(allp).all(1)]
    if not len(allp):
        return 1.0
    d = float(np.linalg.norm(allp.max(0) - allp.min(0)))
    return d if d > 0 else 1.0


def view_directions(points: np.ndarray, eye) -> np.ndarray:
    """[N, 3] unit directions from each point towards the eye (0 where they coincide)."""
    v = np.asarray(eye, np.float64)[None, :] - points
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v), where=length > 0)


def reflect(view: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[N, 3] mirror directions r = 2(n·v)n − v (unit when n and v are)."""
    return 2 * np.einsum("ij,ij->i", normals, view)[:, None] * normals - view


def dot3(vectors: np.ndarray, directions: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """[n, M] float64 dot products of ``vectors`` [n, 3] with ``directions`` [M, 3].

    Matrix products of at most ``GEMM_SINGLE`` multiply-adds each: OpenBLAS runs
    those on the calling thread, so worker threads calling this at once do not stall
    on OpenBLAS's own thread pool (a whole [N, 3]·[3, M] product would be split over
    threads).  Culling and shading both use this one function, so a pair's n·ω and
    r·ω are bit-identical in both.
    """
    v = np.asarray(vectors, np.float64)
    d_t = np.asarray(directions, np.float64).T
    if out is None:
        out = np.empty((len(v), d_t.shape[1]))
    step = max(1, GEMM_SINGLE // max(1, 3 * d_t.shape[1]))
    for s in range(0, len(v), step):
        np.matmul(v[s:s + step], d_t, out=out[s:s + step])
    return out


def matvec(a: np.ndarray, x: np.ndarray) -> np.ndarray:
    """a @ x ([b, M] · [M]) without BLAS, whose matrix-vector product goes multithreaded
    at far smaller sizes than its matrix product (see :func:`dot3`)."""
    return np.einsum("ij,j->i", a, x)
