"""Bake texel-aligned shading features: ``relight bake-features`` as an engine job.

:func:`bake` takes a loaded hand recording (a :class:`~relight_cli.hand.model.HandData`,
one or two hands) and loaded env maps (:class:`~relight_cli.formats.envmap.EnvMap`) and
yields one :class:`BakedFrame` per selected frame: for each env map the texel-aligned
layers (RelightableHands' diffuse and Phong, URHand's GGX, visibility, mask) and the
per-vertex features, with the settings the provenance records.  Visibility is traced
once per pose against every hand and reused for every env map; the UV rasterizations
are shared by every pose.  Writing is the caller's
(:func:`relight_cli.formats.features_exr.write_features`, ``write_vertex_features``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from relight_cli.envmap import DEFAULT_GRID


@dataclass
class BakeOptions:
    """What to bake (``relight bake-features``' options).

    settings: :class:`relight_cli.features.FeatureSettings` (shininess, specular model,
        visibility, a scalar GGX roughness).
    env_res: (H, W) lat-long grid the env maps are integrated over.
    tex_res: (H, W) of the texel maps.  mesh: ``coarse`` (the proxy) or ``fine``.
    viewer: the viewer's world position [3], or None: the centre of the default camera
        framing each frame's posed hands from the front (+Z).
    roughness_map: [H, W] UV-space GGX roughness in (0, 1] (sampled at each vertex's UV),
        overriding ``settings.roughness``; or None.
    roughness_label: what the provenance records as ``roughness`` (the command's option
        text); None records the scalar (or ``map``).
    env_sources: bright sources taken out of each env map before the grid
        (:func:`relight_cli.envmap.discretize_env`): ``"auto"``, ``"none"`` or a count; the
        physical renderer's rule, so its env transport and these features agree.
    """

    settings: object
    env_res: tuple = DEFAULT_GRID
    tex_res: tuple = (128, 128)
    mesh: str = "coarse"
    viewer: object = None
    roughness_map: object = None
    roughness_label: object = None
    env_sources: object = "auto"


@dataclass
class BakedFrame:
    """One frame's features.

    maps[k]: env map k's layers, name → [H, W] float32 texel map (one hand plain, two
        prefixed ``right.`` / ``left.``), as ``write_features`` takes them.
    vertex[k]: env map k's per-vertex arrays (``vertices``, ``faces``, ``normals`` and a
        [V] array per feature, per hand, prefixed as ``maps``), as
        ``write_vertex_features`` takes them.
    viewer: [3] float64 viewer position.  hands: the posed hands' names.
    rays_traced: visibility rays traced for this pose.  seconds: per-stage timings.
    settings: the provenance settings of this frame (shared by every env map).
    """

    frame: int
    maps: list
    vertex: list
    viewer: np.ndarray
    hands: list
    rays_traced: int
    seconds: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def bake(data, frames, envs, options: BakeOptions, names=None, source: str = "",
         quiet: bool = True):
    """Features of ``data``'s ``frames`` under each EnvMap of ``envs``: an iterator of
    :class:`BakedFrame`.

    The env maps are discretized on ``options.env_res`` and checked at once (a map whose
    features would overflow float32 is a DataError naming ``names[k]``, env map k's
    name in errors; default its own), before the iterator is returned; the frames are
    baked as it is consumed (a frame bar on stderr unless ``quiet`` or a single frame).
    ``source``: the hand's name in errors.
    """
    from relight_cli.envmap import discretize_env, share_directions
    from relight_cli.errors import DataError

    names = list(names) if names is not None else [e.name for e in envs]
    h, w = options.env_res
    t0 = time.perf_counter()
    # every map's bright sources join one direction set: visibility is traced once for all
    discrete = share_directions([discretize_env(e, h, w, sources=options.env_sources)
                                 for e in envs])
    env_seconds = time.perf_counter() - t0
    for d, spec in zip(discrete, names):
        # Every layer is at most ~1e3 × the map's power Σ L Δω (the sharpest Phong/GGX
        # lobes): beyond float32's range the stored features would be Inf.
        power = float((d.radiance * d.solid_angle[:, None]).sum(axis=0).max())
        if not power * 1e3 < float(np.finfo(np.float32).max):
            raise DataError(f"env map is too bright (power {power:.3g}): its features would "
                            f"overflow float32", spec)
    return _frames(data, list(frames), discrete, options, names, source,
                   {"env": env_seconds}, quiet)


def _frames(data, frames, discrete, options, names, source, seconds, quiet):
    from relight_cli.bake import PoseFeatures
    from relight_cli.errors import DataError
    from relight_cli.progress import progress

    rasters = {}     # UV rasterizations: pose independent, made once
    for fr in progress(frames, desc="frames", quiet=quiet or len(frames) == 1):
        pose = PoseFeatures(data, fr, options.settings, options.env_res, options.tex_res,
                            options.mesh, rasters, source=source,
                            grid=discrete[0] if discrete[0].sources else None)
        posed = pose.posed
        viewer = pose.default_viewer() if options.viewer is None else options.viewer
        rough = None
        if options.roughness_map is not None:
            rough = np.concatenate([sample_uv_map(options.roughness_map, pm) for pm in posed])
        results, texel = pose.bake(discrete, viewer, roughness=rough)
        maps = [pose.layers(per_mesh) for per_mesh in texel]
        for layers, spec in zip(maps, names):
            overflow = [n for n, value in layers.items() if not np.isfinite(value).all()]
            if overflow:  # e.g. radiance near float32's limit: the sums overflow
                raise DataError(f"features overflow float32 in layer(s) {', '.join(overflow)} "
                                f"(env map radiance too large)", spec)
        yield BakedFrame(fr, maps, [_vertex_arrays(posed, per_env) for per_env in results],
                         viewer, [pm.name for pm in posed], int(pose.baker.stats.rays_traced),
                         {**seconds, **pose.stats}, _settings(fr, options, viewer))


def _settings(frame, options: BakeOptions, viewer) -> dict:
    s = options.settings
    label = options.roughness_label
    if label is None:
        label = "map" if options.roughness_map is not None else s.roughness
    return {"frame": frame, "mesh": options.mesh,
            "env_res": [options.env_res[0], options.env_res[1]],
            "res": [options.tex_res[1], options.tex_res[0]], "shininess": list(s.phong),
            "specular": s.specular, "roughness": label, "visibility": s.visibility,
            "ggx_shadowing": s.shadowing, "env_sources": options.env_sources,
            "view": [float(x) for x in viewer]}


def _vertex_arrays(posed, per_mesh) -> dict:
    arrays = {}
    for pm, feats in zip(posed, per_mesh):
        prefix = "" if len(posed) == 1 else pm.name + "."
        arrays[prefix + "vertices"] = pm.vertices
        arrays[prefix + "faces"] = pm.faces
        arrays[prefix + "normals"] = pm.normals
        for name, value in feats.items():
            arrays[prefix + name] = value
    return arrays


def sample_uv_map(image, pm):
    """[V] bilinear samples of a UV-space map [H, W] at each vertex's (first) UV of the
    posed mesh ``pm``."""
    h, w = image.shape
    uv_of_vertex = np.zeros((len(pm.vertices), 2))
    uv_of_vertex[pm.faces.ravel()] = pm.uv[pm.faces_uv.ravel()]
    x = np.clip(uv_of_vertex[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv_of_vertex[:, 1]) * h - 0.5, 0, h - 1)   # v = 0 at the bottom row
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    return ((image[y0, x0] * (1 - fx) + image[y0, x1] * fx) * (1 - fy)
            + (image[y1, x0] * (1 - fx) + image[y1, x1] * fx) * fy)
