"""The one embree wrapper: occlusion and closest-hit queries on triangle meshes.

Everything that traces rays (visibility features, G-buffers, shadow rays,
pseudo-ground-truth shadows) goes through :class:`RayScene`, which batches
queries into large embree calls.  ``occluded_reference`` is the slow, obviously
correct twin (trimesh's pure-numpy triangle tests) that tests compare against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Rays are split into chunks so peak memory stays bounded (embreex copies inputs).
_CHUNK = 1 << 21


@dataclass
class Hits:
    """Closest hits of a ray batch.

    Attributes:
        hit: [N] bool.
        t: [N] float32 distance along the (unit) direction; inf where no hit.
        face: [N] int64 triangle index into the concatenated faces; -1 where no hit.
        mesh: [N] int64 index of the mesh (order given to RayScene); -1 where no hit.
        barycentric: [N, 3] float32 weights of the triangle's 3 vertices.
    """

    hit: np.ndarray
    t: np.ndarray
    face: np.ndarray
    mesh: np.ndarray
    barycentric: np.ndarray


class RayScene:
    """A static embree scene of one or more triangle meshes (e.g. two hands).

    Args:
        meshes: list of (vertices [V, 3] float, faces [F, 3] int) in world space.
    """

    def __init__(self, meshes):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self._scene = rtcore_scene.EmbreeScene()
        self.face_offsets = [0]
        self.rays_traced = 0
        for vertices, faces in meshes:
            vertices = np.ascontiguousarray(vertices, dtype=np.float32)
            faces = np.ascontiguousarray(faces, dtype=np.int32)
            if len(faces) == 0:
                continue
            TriangleMesh(self._scene, vertices, faces)
            self.face_offsets.append(self.face_offsets[-1] + len(faces))
        self.n_meshes = len(self.face_offsets) - 1

    def occluded(self, origins: np.ndarray, directions: np.ndarray,
                 t_far: np.ndarray | float | None = None) -> np.ndarray:
        """[N] bool: does the segment origin + t·direction, 0 < t < t_far, hit anything?

        Args:
            origins: [N, 3] world positions (offset them off the surface yourself).
            directions: [N, 3] unit directions.
            t_far: [N] or scalar segment length; None = infinite.
        """
        origins = np.asarray(origins, np.float32).reshape(-1, 3)
        directions = np.asarray(directions, np.float32).reshape(-1, 3)
        n = len(origins)
        out = np.zeros(n, bool)
        if n == 0 or self.n_meshes == 0:
            return out
        if t_far is not None:
            # a writable copy: embree refuses read-only (broadcast) buffers
            t_far = np.array(np.broadcast_to(np.asarray(t_far, np.float32), (n,)))
        for start in range(0, n, _CHUNK):
            sl = slice(start, min(n, start + _CHUNK))
            o = np.ascontiguousarray(origins[sl])
            d = np.ascontiguousarray(directions[sl])
            if t_far is None:
                res = self._scene.run(o, d, query="OCCLUDED")
            else:
                res = self._scene.run(o, d, dists=np.ascontiguousarray(t_far[sl]), query="OCCLUDED")
            out[sl] = np.asarray(res) != -1
        self.rays_traced += n
        return out

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """Closest hits of rays with unit ``directions`` from ``origins`` ([N, 3] each)."""
        origins = np.asarray(origins, np.float32).reshape(-1, 3)
        directions = np.asarray(directions, np.float32).reshape(-1, 3)
        n = len(origins)
        face = np.full(n, -1, np.int64)
        mesh = np.full(n, -1, np.int64)
        t = np.full(n, np.inf, np.float32)
        bary = np.zeros((n, 3), np.float32)
        if n and self.n_meshes:
            offsets = np.asarray(self.face_offsets, np.int64)
            for start in range(0, n, _CHUNK):
                sl = slice(start, min(n, start + _CHUNK))
                r = self._scene.run(np.ascontiguousarray(origins[sl]),
                                    np.ascontiguousarray(directions[sl]), output=1)
                prim = np.asarray(r["primID"], np.int64)
                geom = np.asarray(r["geomID"], np.int64)
                ok = prim >= 0
                face[sl][ok] = prim[ok] + offsets[geom[ok]]
                mesh[sl][ok] = geom[ok]
                t[sl][ok] = np.asarray(r["tfar"])[ok]
                u = np.asarray(r["u"], np.float32)
                v = np.asarray(r["v"], np.float32)
                b = np.stack([1 - u - v, u, v], axis=1)
                bary[sl][ok] = b[ok]
            self.rays_traced += n
        return Hits(hit=face >= 0, t=t, face=face, mesh=mesh, barycentric=bary)


def occluded_reference(vertices, faces, origins, directions, t_far=None) -> np.ndarray:
    """Slow twin of :meth:`RayScene.occluded`: brute-force Möller–Trumbore in float64.

    For tests only: every ray against every triangle, in chunks (O(N·F) work).
    Same argument meanings as :meth:`RayScene.occluded`.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]      # [F, 3, 3]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    origins = np.asarray(origins, np.float64).reshape(-1, 3)
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    n = len(origins)
    limit = np.full(n, np.inf) if t_far is None else np.broadcast_to(
        np.asarray(t_far, np.float64), (n,))
    out = np.zeros(n, bool)
    chunk = max(1, 2_000_000 // max(1, len(tri)))
    for start in range(0, n, chunk):
        o = origins[start:start + chunk, None, :]                           # [c, 1, 3]
        d = directions[start:start + chunk, None, :]
        p = np.cross(d, e2[None])                                           # [c, F, 3]
        det = np.einsum("cfk,fk->cf", p, e1)
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - v0[None]
        u = np.einsum("cfk,cfk->cf", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("cfk,cfk->cf", np.broadcast_to(d, q.shape), q) * inv
        t = np.einsum("cfk,fk->cf", q, e2) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < limit[start:start + chunk, None])
        out[start:start + chunk] = hit.any(axis=1)
    return out
