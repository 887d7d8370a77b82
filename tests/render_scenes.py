"""Small analytic scenes for the renderer tests (UV sphere, UV quad)."""

from __future__ import annotations

import numpy as np

from relight_cli.hand.scene import PosedMesh


def uv_sphere(radius=0.05, centre=(0.0, 0.0, 0.0), n_lat=32, n_lon=64) -> PosedMesh:
    """A closed lat-long sphere with a lat-long UV map and exact normals.

    Vertices on the seam are duplicated (their positions are bit-identical, so
    the surface stays watertight for ray tracing); the poles are single vertices.
    """
    centre = np.asarray(centre, np.float64)
    theta = np.linspace(0, np.pi, n_lat + 1)[1:-1]               # interior rings
    phi = np.linspace(0, 2 * np.pi, n_lon + 1)                   # n_lon + 1 columns (seam twice)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(tt) * np.cos(pp), np.cos(tt), -np.sin(tt) * np.sin(pp)], -1)
    ring[:, -1] = ring[:, 0]                                     # identical seam positions
    dirs = np.concatenate([[[0, 1.0, 0]], ring.reshape(-1, 3), [[0, -1.0, 0]]])
    uv_ring = np.stack(np.meshgrid(phi / (2 * np.pi), 1 - theta / np.pi, indexing="xy"), -1)
    uv = np.concatenate([[[0.5, 1.0]], uv_ring.reshape(-1, 2), [[0.5, 0.0]]])
    cols = n_lon + 1

    def vid(r, c):
        return 1 + r * cols + c

    faces = []
    for c in range(n_lon):
        faces.append([0, vid(0, c), vid(0, c + 1)])
        for r in range(n_lat - 2):
            a, b, cc, d = vid(r, c), vid(r + 1, c), vid(r + 1, c + 1), vid(r, c + 1)
            faces += [[a, b, cc], [a, cc, d]]
        last = len(dirs) - 1
        faces.append([vid(n_lat - 2, c), last, vid(n_lat - 2, c + 1)])
    faces = np.asarray(faces, np.int64)
    verts = centre + radius * dirs
    # Orient outward.
    tri = verts[faces] - centre
    if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
        faces = faces[:, [0, 2, 1]]
    return PosedMesh(verts, faces, uv, faces.copy(), dirs.copy(), "sphere")


def uv_quad(size=0.2, z=0.0) -> PosedMesh:
    """A square in the plane z = ``z`` facing +z, UV (0,0) at (−s/2, −s/2)."""
    h = size / 2
    verts = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    return PosedMesh(verts, faces, uv, faces.copy(), normals, "quad")
