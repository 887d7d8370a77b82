"""Relight Gaussians: the Gaussian mode of ``relight relight`` as engine jobs.

    relight(...)        objects relit by an SH probe (paper Eq. 9-10), optionally lit
                        directly by a DGSM's lights, receivers and objects shadowed by
                        the DGSM (Sec. 3.3), optionally rendered from a camera
    shadow_matte(...)   the receivers-only shadow matte of the paper's Sec. 4.2

Relighting a capture where it stands (issue 53):

    env_probe(...)         an env map's SH probe, fitted as ``relight sh-probe`` fits it,
                           at the degree the transfer's lobe needs (transfer_degree)
    upright_rotation(...)  the rotation taking a capture whose up axis is ``up`` upright
    lighting_in_frame(...) a world (+Y up) probe turned into that capture's frame
    in_source_frame(...)   placed, relit Gaussians written back in their source's frame

Both take what the command has read (Gaussians, an SH probe, a DGSM, a camera) and an
options dataclass, and return arrays plus the settings the provenance records; logging
goes through the ``log`` callable given (none by default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def _quiet(message: str) -> None:
    pass


@dataclass
class GaussianOptions:
    """``relight relight``'s Gaussian options (see its --help).

    shadow_strength: a number in [0, 1] or ``"auto"``.  light_weights: ``intensity``,
    ``irradiance``, ``equal`` or None (irradiance with auto strength, else intensity).
    t_max: the shading clip (None: no clip)."""

    lobe: float = 1.0
    intensity: float = 1.0
    t_max: float | None = None
    normals: str = "auto"
    footprint: str = "stencil"
    samples: int = 16
    seed: int = 0
    shadow_strength: float | str = "auto"
    light_weights: str | None = None
    direct_light: bool = False
    self_shadow: bool = False


@dataclass
class RelitGaussians:
    """What :func:`relight` returns: the relit ``objects`` (one Gaussians, the inputs
    concatenated in order), the shadowed ``receivers`` (or None), with a camera the
    rendered ``channels`` (R, G, B, A) and ``rgb`` [H, W, 3] (else None), and the
    ``settings`` the provenance records (the command adds the objects' specs and, for an
    image, the background)."""

    objects: object
    receivers: object | None
    settings: dict
    channels: dict | None = None
    rgb: np.ndarray | None = None
    rendered: int = 0


@dataclass
class Matte:
    """What :func:`shadow_matte` returns: the image ``channels`` and ``rgb``, each
    receiver's shadow ``strength`` [M] and the provenance ``settings``."""

    channels: dict
    rgb: np.ndarray
    strength: np.ndarray
    settings: dict = field(default_factory=dict)


#: ``--up`` axis names → the proper rotation U [3, 3] taking that axis to +Y, exactly (integer
#: entries): the minimal rotation about an axis perpendicular to both, and for -y the half turn
#: about x (the OpenCV/COLMAP → OpenGL flip diag(1, -1, -1), = placement rotate-x=180).
UP_AXES = {
    "+y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "+z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "+x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
}
#: Share of the transfer lobe's SH energy a probe fitted from an env map keeps (transfer_degree).
LOBE_ENERGY = 0.99
#: The highest degree transfer_degree picks (relight sh-probe's --degree range).
MAX_ENV_DEGREE = 8


def upright_rotation(up) -> np.ndarray:
    """[3, 3] proper rotation U with U·up = +Y: ``up`` an axis name of :data:`UP_AXES` or a
    3-vector (any length > 0) in the capture's own coordinates.  A vector with up_y ≥ 0 takes
    the minimal rotation (about up × Y); one pointing downwards is first flipped as "-y" is
    (the half turn about x), then tilted minimally, so a COLMAP capture's slightly tilted up
    is "-y" plus a small correction (and both branches are well conditioned).  Raises
    ValueError for an unknown name or a zero/non-finite vector."""
    if isinstance(up, str):
        key = up.strip().lower()
        key = key if key[:1] in "+-" else "+" + key
        if key not in UP_AXES:
            raise ValueError(f"up must be one of {', '.join(UP_AXES)} or X,Y,Z, got {up!r}")
        return np.array(UP_AXES[key], np.float64)
    u = np.asarray(up, np.float64).reshape(3)
    length = float(np.linalg.norm(u))
    if not (math.isfinite(length) and length > 0):
        raise ValueError(f"up must be a finite non-zero vector, got {list(u)}")
    u = u / length
    if u[1] < 0:
        flip = np.array(UP_AXES["-y"], np.float64)
        return _minimal_rotation_to_y(flip @ u) @ flip
    return _minimal_rotation_to_y(u)


def _minimal_rotation_to_y(u: np.ndarray) -> np.ndarray:
    """[3, 3] the rotation about u × Y taking unit ``u`` (u_y ≥ 0) to +Y (Rodrigues, with
    1 − cos θ = sin²θ / (1 + cos θ), 1 + cos θ ≥ 1 here)."""
    axis = np.cross(u, [0.0, 1.0, 0.0])                 # |axis| = sin θ
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + k + k @ k / (1 + float(u[1]))


def lighting_in_frame(coefficients, upright: np.ndarray) -> np.ndarray:
    """[(d+1)², 3] SH radiance L of the world (+Y up) → L_c(d) = L(U d), the same light in
    the frame of a capture that ``upright`` (U, :func:`upright_rotation`) takes upright.
    Relighting the capture under L_c is relighting it placed upright by U under L, then
    moved back: the lighting turns, the data stay where they are."""
    from relight_cli.gaussians.placement import rotate_sh
    c = np.asarray(coefficients, np.float64)
    return rotate_sh(c[None], np.asarray(upright, np.float64).T)[0]


def transfer_degree(lobe: float, energy: float = LOBE_ENERGY,
                    max_degree: int = MAX_ENV_DEGREE) -> int:
    """The smallest SH degree L whose bands hold ``energy`` of the transfer lobe's SH energy
    Σ_l (2l+1) a_l(q)² (a_l the Funk–Hecke factors of max(n·ω, 0)^q, relight_cli.gaussians.
    transfer): shading from a probe of degree L misses the rest, whatever the env map.  q = 1
    (Lambertian) gives 2 (99.2 %), q = 3 gives 3, q = 10 gives 6; at most ``max_degree``."""
    from relight_cli.gaussians.transfer import lobe_band_factors
    a = lobe_band_factors(lobe, 256)
    band = (2 * np.arange(257) + 1) * a ** 2
    held = np.cumsum(band) / band.sum()
    return int(min(int(np.argmax(held >= energy)), max_degree))


def env_probe(env, lobe: float, source: str = "", log=_quiet):
    """The SH probe (formats.sh_probe_json.ShProbe) of an env map (envmap.EnvMap) for a
    transfer of lobe exponent ``lobe``: fitted by :func:`relight_cli.jobs.sh_probe.fit`
    exactly as ``relight sh-probe ENV --degree L`` fits it (ridge 0), L =
    :func:`transfer_degree`."""
    from relight_cli.formats.sh_probe_json import ShProbe
    from relight_cli.jobs.sh_probe import ProbeOptions, fit
    degree = transfer_degree(lobe)
    probe = fit(env, ProbeOptions(degree=degree))
    log(f"fitted the env map's SH probe at degree {degree} (the transfer lobe q = {lobe:g} "
        f"keeps {100 * LOBE_ENERGY:g} % of its energy there; relight sh-probe fits the same)")
    return ShProbe(np.asarray(probe.coefficients, np.float64), degree, 0.0, source)


def in_source_frame(relit, source, similarity):
    """Relit Gaussians of a placed object (``relit``, scene frame) written back in the frame
    of its ``source`` (the Gaussians before the placement ``similarity``, placement.
    Similarity): geometry and opacity are the source's own arrays (bit for bit), the relit
    colours' view-dependent bands turned back by Qᵀ, the stored normals by Qᵀ.  Relighting
    changes only colours, so the result registers with the source's cameras.  A placement
    that dropped Gaussians (another count) is undone by the inverse similarity instead
    (geometry to float64 round-off)."""
    from relight_cli.formats.gaussians_ply import Gaussians
    from relight_cli.gaussians.placement import Similarity, rotate_sh, transform_gaussians
    Q = np.asarray(similarity.rotation, np.float64)
    if len(relit) != len(source):
        inverse = Similarity(1.0 / similarity.scale, Q.T,
                             -(Q.T @ np.asarray(similarity.translation, np.float64))
                             / similarity.scale)
        return transform_gaussians(relit, inverse)
    sh = relit.sh if relit.sh_degree == 0 else rotate_sh(relit.sh, Q.T)
    normals = None if relit.normals is None else relit.normals @ Q      # Qᵀ n, row-wise
    return Gaussians(source.means, source.scales, source.rotations, source.opacities, sh,
                     relit.sh_degree, normals, source_colour_space=relit.source_colour_space)


def weights_mode(light_weights: str, shadow_map, log=_quiet) -> str:
    """``light_weights`` as it can run with this shadow map (version 1 maps: equal, said)."""
    from relight_cli.gaussians import transfer as TF
    mode = TF.effective_light_weights(light_weights, shadow_map.intensities)
    if mode != light_weights:
        log("note: this shadow map (DGSM version 1) stores no light intensities; the lights "
            "are weighted equally")
    return mode


def relight(objects, probe, options: GaussianOptions, shadow_map=None, receivers=None,
            camera=None, background=(0.0, 0.0, 0.0), names=None, log=_quiet,
            quiet: bool = True) -> RelitGaussians:
    """Relight ``objects`` (a list of Gaussians, IN then each --object) by ``probe`` (an
    SH probe: ``coefficients``, ``degree``; or a list of them, one per object: each
    object's local light, as a clip refits them at the objects' positions, the first
    also lighting the receivers' auto shadow strength).  With ``shadow_map`` (a DGSM) the
    ``receivers`` (Gaussians, required then) are shadowed and, for a grouped DGSM, each
    object by the others; with ``camera`` receivers + objects are rendered over
    ``background``.  ``names``: each object's name in errors (a DataError for normals
    that cannot be estimated).  ``quiet`` False: a long render shows progress on stderr
    (relight_cli.gaussians.splat.render)."""
    from relight_cli.formats.gaussians_ply import concatenate

    o = options
    names = names or [f"object {j}" for j in range(len(objects))]
    if shadow_map is not None and receivers is None:
        raise ValueError("a shadow map shadows receivers: give receivers")
    if o.direct_light and shadow_map is None:
        raise ValueError("direct_light takes its lights from a shadow map")
    if o.self_shadow and shadow_map is None:
        raise ValueError("self_shadow looks the objects up in a shadow map: give one")
    if shadow_map is not None and shadow_map.groups is not None \
            and len(shadow_map.groups) != len(objects):
        raise ValueError(f"the shadow map has {len(shadow_map.groups)} occluder groups but "
                         f"{len(objects)} object(s) were given")
    auto, strength_setting = o.shadow_strength == "auto", o.shadow_strength
    if auto and shadow_map is not None and shadow_map.intensities is None:
        log("note: this shadow map (DGSM version 1) stores no light intensities, so "
            "--shadow-strength auto cannot weigh them against the probe: s = 1")
        auto, strength_setting = False, 1.0
    light_weights = o.light_weights or ("irradiance" if auto else "intensity")
    probes = list(probe) if isinstance(probe, (list, tuple)) else [probe] * len(objects)
    if len(probes) != len(objects):
        raise ValueError(f"{len(probes)} probes for {len(objects)} objects")
    probe = probes[0]
    relit, direct = _relit_objects(objects, probes, o, shadow_map, names)
    log(f"probe degree {probe.degree}" + (", objects lit by the shadow map's "
                                          f"{len(shadow_map.lights)} light(s) too"
                                          if o.direct_light else ""))
    settings = {"lobe": o.lobe, "intensity": o.intensity, "t_max": o.t_max,
                "normals": o.normals, "footprint": o.footprint, "samples": o.samples,
                "seed": o.seed, "shadow_strength": strength_setting,
                "direct_light": o.direct_light,
                **({"self_shadow": True} if o.self_shadow else {})}
    if shadow_map is not None:
        used = weights_mode(light_weights, shadow_map, log)
        receivers = _shadow_receivers(receivers, probe, shadow_map, used, auto,
                                      strength_setting, o, log)
        _shadow_objects(relit, direct, probes, shadow_map, used, auto, strength_setting, o,
                        log)
        # which opacity mapping made the shadow map, and how its lights were weighted
        settings.update(dgsm_mapping=shadow_map.mapping, dgsm_kappa=shadow_map.kappa,
                        light_weights=used)
    out = RelitGaussians(relit[0] if len(relit) == 1 else concatenate(relit), receivers,
                         settings)
    if camera is not None:
        from relight_cli.gaussians.splat import render
        everything = out.objects if receivers is None else concatenate([receivers, out.objects])
        image = render(everything, camera, background=background, quiet=quiet)
        out.channels = _rgba(image)
        out.rgb, out.rendered = image.image.astype(np.float32), len(everything)
    return out


def _relit_objects(objects, probes, o: GaussianOptions, shadow_map, names):
    """Each object relit by its probe (+ the DGSM's lights with direct_light): (relit
    list, per object [L, N, 3] irradiance of each light or None)."""
    from relight_cli.errors import DataError
    from relight_cli.gaussians import transfer as TF
    relit, direct = [], []
    for g, name, probe in zip(objects, names, probes):
        try:
            n = TF.estimate_normals(g, o.normals)
        except ValueError as exc:  # e.g. normals stored on a file without normals
            raise DataError(str(exc), name) from None
        d = extra = None
        if o.direct_light:
            d = TF.direct_irradiance(shadow_map.intensities, shadow_map.colors,
                                     shadow_map.lights, g.means, n, one_sided=True)
            extra = d.sum(axis=0) / math.pi
        direct.append(d)
        relit.append(TF.relight_gaussians(
            g, probe.coefficients, q=o.lobe, intensity=o.intensity,
            t_max=math.inf if o.t_max is None else o.t_max, normals=n, extra=extra))
    return relit, direct


def _darkened(factor) -> str:
    return (f"mean factor {factor.mean():.3f}, "
            f"{int((factor.reshape(len(factor), -1).min(axis=1) < 0.99).sum())} of "
            f"{len(factor)} darkened")


def _shadow_receivers(scene, probe, shadow_map, weights_used, auto, strength, o, log):
    """The receivers, each light's share of their direct light attenuated by its
    transmittance (auto strength: per receiver, the lights' share against the probe's;
    relight_cli.gaussians.receiver_shadow, which dgsm-build --preview shares)."""
    from relight_cli.gaussians import transfer as TF
    from relight_cli.gaussians.dgsm import sample_transmittance
    from relight_cli.gaussians.receiver_shadow import receiver_shadow
    T = sample_transmittance(shadow_map, scene.means, scene.scales, scene.rotations,
                             footprint=o.footprint, samples=o.samples, seed=o.seed)   # [L, M]
    shadow = receiver_shadow(shadow_map, scene, T, "auto" if auto else strength, weights_used,
                             probe.coefficients)
    if auto:        # per receiver: the lights' share of its light against the probe's
        strength = shadow.strength
        log(f"direct share of the receivers' light (auto): median "
            f"{float(np.median(strength)):.2f}, range {float(strength.min()):.2f}–"
            f"{float(strength.max()):.2f}")
    factor = shadow.factor  # [M, 3]
    log(f"shadowed receivers: {_darkened(factor)}")
    return TF.attenuate(scene, factor)


def _shadow_objects(relit, direct, probes, shadow_map, weights_used, auto, strength, o, log):
    """Each object (in place in ``relit``) shadowed by the others (a grouped DGSM); with
    ``o.self_shadow`` by the others and by itself, each Gaussian's own optical depth left
    out (relight_cli.gaussians.dgsm.sample_self_transmittance; ours, beyond the paper)."""
    from relight_cli.gaussians import transfer as TF
    from relight_cli.gaussians.dgsm import sample_self_transmittance, sample_transmittance
    if o.self_shadow:
        if not all(record.get("self_shadow") for record in shadow_map.roi):
            raise ValueError("the shadow map was not built for self-shadowing: its tables do "
                             "not cover the objects' own lookups (dgsm-build --self-shadow)")
    elif shadow_map.groups is None:
        if len(relit) > 1:
            log("note: the shadow map has no occluder groups, so the objects do not shadow "
                "each other (build it from all objects: dgsm-build A B ...)")
        return
    for j, obj in enumerate(relit):
        if auto and direct[j] is None:
            continue    # lit by the probe only: the lights' shadows do not reach it
        if o.self_shadow:
            T = sample_self_transmittance(shadow_map, obj.means, obj.scales, obj.rotations,
                                          footprint=o.footprint, samples=o.samples, seed=o.seed)
        else:
            T = sample_transmittance(shadow_map.others(j), obj.means, obj.scales, obj.rotations,
                                     footprint=o.footprint, samples=o.samples, seed=o.seed)
        if auto:        # colour ρ(S + D): direct share D/(S + D), weights D_l (exact)
            d = direct[j].sum(axis=0) / math.pi
            probe_part = np.clip(TF.shading(probes[j].coefficients, obj.normals, o.lobe), 0.0,
                                 None)
            total = probe_part + d
            share = np.where(total > 0, d / np.where(total > 0, total, 1), 0.0)
            factor = TF.shadow_factor(T, direct[j], share)
        else:
            weights = TF.dgsm_light_weights(weights_used, shadow_map, obj, obj.normals)
            factor = TF.shadow_factor(T, weights, strength)
        relit[j] = TF.attenuate(obj, factor)
        log(f"shadowed object {j} by " + ("the others and itself" if o.self_shadow
                                           else "the others") + f": {_darkened(factor)}")


def shadow_matte(mode: str, receivers, shadow_map, camera, options: GaussianOptions,
                 meshes=None, background=(0.0, 0.0, 0.0), log=_quiet,
                 quiet: bool = True) -> Matte:
    """The receivers-only shadow matte (paper Sec. 4.2): receivers coloured by shadow
    strength 1 − Σ w_l V_l / Σ w_l, nothing else drawn.  ``mode`` ``dgsm``: V the DGSM's
    transmittance; ``mesh``: embree shadow rays against ``meshes`` (the objects as
    triangle meshes).  Lights and weights (``options.light_weights``, default intensity)
    come from the DGSM; ``quiet`` as :func:`relight`'s."""
    from relight_cli.gaussians import dgsm as D
    from relight_cli.gaussians import shadow_matte as SM
    from relight_cli.gaussians import transfer as TF
    from relight_cli.gaussians.splat import render

    o, scene = options, receivers
    used = weights_mode(o.light_weights or "intensity", shadow_map, log)
    weights = TF.dgsm_light_weights(used, shadow_map, scene)
    if mode == "dgsm":
        V = D.sample_transmittance(shadow_map, scene.means, scene.scales, scene.rotations,
                                   footprint=o.footprint, samples=o.samples, seed=o.seed)
    elif mode == "mesh":
        if meshes is None:
            raise ValueError("a mesh shadow matte needs the objects' meshes")
        pts, n = D.footprint_samples(scene.means, scene.scales, scene.rotations, o.footprint,
                                     o.samples, o.seed)
        V = SM.mesh_visibility(meshes, shadow_map.lights, pts.reshape(-1, 3))
        V = V.reshape(len(shadow_map.lights), len(scene), n).mean(axis=2)
    else:
        raise ValueError(f"shadow matte mode is dgsm or mesh, got {mode!r}")
    strength = SM.shadow_strength(TF.shadow_factor(V, weights, 1.0))
    image = render(scene, camera, background=background, colors=SM.matte_colors(strength),
                   quiet=quiet)
    settings = {"shadow_matte": mode, "footprint": o.footprint, "samples": o.samples,
                "seed": o.seed, "light_weights": used, "dgsm_mapping": shadow_map.mapping}
    return Matte(_rgba(image), image.image.astype(np.float32), strength, settings)


def _rgba(image) -> dict:
    return {"R": image.image[..., 0], "G": image.image[..., 1], "B": image.image[..., 2],
            "A": image.alpha}
