"""bake-features' per-frame pipeline as one engine object: pose → trace → transport → texel maps.

``relight bake-features`` and the RelightableHands student (``relight distill``,
``relight --model student``) both call :class:`PoseFeatures`, so the student sees
exactly the features the command writes:

1. pose every hand of the scene at a frame (LBS, coarse proxy by default), refusing
   non-finite vertices;
2. a :class:`relight_cli.features.FeatureBaker` per pose: visibility traced once
   against every hand and reused for every env map and viewer (per-vertex diffuse,
   Phong and GGX features, RelightableHands Eq. 8–9);
3. barycentric interpolation of the per-vertex features into each hand's UV layout
   (:func:`relight_cli.features.texel_maps`, dilation-filled outside the charts).
"""

from __future__ import annotations

import time

import numpy as np

from relight_cli import features as FE
from relight_cli.envmap import DEFAULT_GRID
from relight_cli.errors import DataError


def pose_scene(hand, frame: int, mesh: str = "coarse", source: str = "") -> list:
    """Every hand of ``hand`` posed at ``frame`` (``PosedMesh`` list); DataError naming
    ``source`` for a frame that cannot be posed or non-finite posed vertices."""
    from relight_cli.hand.scene import posed_meshes
    try:
        posed = posed_meshes(hand, frame, mesh)
    except (IndexError, ValueError) as exc:
        raise DataError(f"cannot pose frame {frame}: {exc}", source) from None
    for pm in posed:
        if not np.isfinite(pm.vertices).all():
            raise DataError(f"frame {frame}: posed vertices hold NaN/Inf", source)
    return posed


class PoseFeatures:
    """Texel-aligned features of one posed scene (one or more hands).

    Args:
        hand: HandData.  frame: frame index.
        settings: :class:`relight_cli.features.FeatureSettings`.
        env_res: (H, W) direction grid of the env maps.
        tex_res: (H, W) of the texel maps.
        mesh: "coarse" (bake-features' default proxy) or "fine".
        rasters: a dict shared across poses caching UV rasterizations (pose independent).
        source: the hand's path, named in errors.
        posed: already posed meshes (skips step 1).
        grid: the DiscreteEnv whose directions the env maps share (with their bright
            sources, :func:`relight_cli.envmap.share_directions`), instead of ``env_res``.
    """

    def __init__(self, hand, frame: int, settings: FE.FeatureSettings, env_res=DEFAULT_GRID,
                 tex_res=(128, 128), mesh: str = "coarse", rasters: dict | None = None,
                 source: str = "", posed=None, grid=None):
        t0 = time.perf_counter()
        if posed is None:
            posed = pose_scene(hand, frame, mesh, source)
        self.posed = posed
        self.frame = frame
        self.tex_res = (int(tex_res[0]), int(tex_res[1]))
        self.rasters = {} if rasters is None else rasters
        self.seconds = {"pose": time.perf_counter() - t0}
        meshes = [FE.PoseMesh(pm.vertices, pm.faces, pm.normals, pm.name) for pm in posed]
        self.baker = FE.FeatureBaker(meshes, settings, env_res=env_res, grid=grid)

    @property
    def names(self) -> list[str]:
        return [pm.name for pm in self.posed]

    def default_viewer(self) -> np.ndarray:
        """The centre of bake-features' default camera (framing the hands from +Z)."""
        from relight_cli.hand.scene import preview_camera
        return preview_camera(self.posed).center

    def vertex_features(self, envs: list, viewer, roughness=None) -> list[list[dict]]:
        """``result[env][mesh]``: per-vertex features (see ``FeatureBaker.bake``)."""
        return self.baker.bake(envs, viewer, roughness=roughness)

    def texel_maps(self, results: list[list[dict]]) -> list[list[dict]]:
        """``maps[env][mesh]``: name → [H, W(, 3)] float32 texel maps, plus ``mask``."""
        from relight_cli.uvraster import rasterize_uv

        t0 = time.perf_counter()
        out = []
        for per_mesh in results:
            maps = []
            for pm, feats in zip(self.posed, per_mesh):
                key = (pm.uv.shape, pm.uv.tobytes(), pm.faces_uv.tobytes(), self.tex_res)
                if key not in self.rasters:
                    self.rasters[key] = rasterize_uv(pm.uv, pm.faces_uv, self.tex_res)
                maps.append(FE.texel_maps(feats, pm.faces, self.rasters[key]))
            out.append(maps)
        self.seconds["texels"] = self.seconds.get("texels", 0.0) + time.perf_counter() - t0
        return out

    def bake(self, envs: list, viewer, roughness=None):
        """(per-vertex results, texel maps) for DiscreteEnvs ``envs`` seen from ``viewer``."""
        results = self.vertex_features(envs, viewer, roughness)
        return results, self.texel_maps(results)

    def layers(self, maps_per_mesh: list[dict]) -> dict:
        """bake-features' EXR layer naming: one hand plain, several prefixed 'right.' …"""
        layers = {}
        for pm, maps in zip(self.posed, maps_per_mesh):
            prefix = "" if len(self.posed) == 1 else pm.name + "."
            for name, value in maps.items():
                layers[prefix + name] = value
        return layers

    @property
    def stats(self) -> dict:
        return {**self.seconds, **self.baker.stats.seconds}
