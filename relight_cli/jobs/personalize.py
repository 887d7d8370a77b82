"""``relight personalize``: a relightable subject from a few photos of a new hand.

URHand Sec. 5.4 and supp. 9: fit the hand to the photos (2D keypoints and masks; pose per
pose group, bone scales shared: :mod:`relight_cli.hand.fit2d`), unwrap the photos into
the UV layout where each texel is seen (visibility- and angle-weighted,
:mod:`relight_cli.neural.unwrap`), fill the holes from the nearest seen texel, divide the
scan's lighting out, and write the subject: the fitted hand.npz carrying its mean texture
T̄, which ``relight … --model linear --checkpoint UNIVERSAL.pt`` renders under any light
without finetuning.

Dividing the lighting out, two ways (``lighting``):

* ``env`` — the scan's environment map is known (an HDRI shot where the scan was taken,
  or the stage's): T̄ = L / E per texel and channel, E the irradiance under the map with
  visibility traced on the fitted hand — the same definition as a light-stage capture's
  T̄ (``albedo_texture``: radiance over the LEDs' irradiance), so the universal model
  sees the units it was trained on.
* ``statistical`` — unknown lighting, the paper's recipe (supp. 9): a one-channel
  shading map fitted in UV space to the unwrapped texture's darkness relative to the
  photos' mean foreground colour, total-variation regularised, divided out.  Its absolute
  level is unknown from the photos, so T̄ is scaled to ``level`` (the mean luminance of
  the universal model's trained subjects' T̄, from its checkpoint): colour and pattern
  come from the scan, brightness from the prior.  This departs from the paper, which
  does not say how its phone textures are brought to the stage's units.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ScanView:
    """One photo: ``name`` (its file), ``camera``, ``image`` [H, W, 3] linear RGB,
    ``mask`` [H, W] bool foreground, ``pose`` its pose group."""

    name: str
    camera: object
    image: np.ndarray
    mask: np.ndarray
    pose: int = 0


@dataclass
class PersonalizeOptions:
    tex_res: int = 256
    iterations: int = 200
    lighting: str = "env"           # env | statistical
    level: float | None = None      # statistical: mean luminance of T̄ (sr⁻¹)
    tv_weight: float = 0.2          # statistical: the shading map's TV weight (test_unwrap)
    env_res: tuple = (32, 64)       # env: the lat-long grid E integrates over
    seed: int = 0


@dataclass
class Personalized:
    """``hand``: the fitted HandData (one frame per pose group) with ``mean_texture``;
    ``fit``: the :class:`~relight_cli.hand.fit2d.Fit2DResult`; ``report``: JSON-ready
    numbers; ``seconds``: wall time per step (for the log, never written)."""

    hand: object
    fit: object
    report: dict
    seconds: dict = field(default_factory=dict)
    radiance: np.ndarray | None = None      # [N, N, 3] the unwrapped (filled) radiance
    seen: np.ndarray | None = None          # [N, N] bool texels some view saw


def personalize(template, views: list, uv: np.ndarray, confidence: np.ndarray, env=None,
                options: PersonalizeOptions | None = None, progress=None) -> Personalized:
    """Fit, unwrap and de-light (see the module docstring).

    Args:
        template: HandData of one hand (its rest pose is used).
        views: V :class:`ScanView`; uv: [V, J, 2] keypoint pixels; confidence: [V, J].
        env: the scan's EnvMap (``lighting="env"``), else None.
        progress: optional callable(stage, step, total).
    """
    from relight_cli.hand.fit2d import Fit2DOptions, fit_views

    opt = options or PersonalizeOptions()
    seconds = {}
    t0 = time.perf_counter()
    groups = np.array([v.pose for v in views], np.int64)
    fit = fit_views(template, [v.camera for v in views], uv, confidence, groups,
                    [v.mask for v in views], Fit2DOptions(iterations=opt.iterations,
                                                          seed=opt.seed), progress)
    seconds["fit"] = time.perf_counter() - t0
    hand = fitted_hand(template, fit)
    t0 = time.perf_counter()
    radiance, irradiance, weight, inside = _unwrap(hand, views, env, opt)
    seconds["unwrap"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    seen = weight > 0
    if opt.lighting == "env":
        from relight_cli.neural.unwrap import divide
        texture = divide(radiance, irradiance, inside)
    else:
        texture = _statistical(radiance, seen, views, opt)
    texture, rejected = reject_outliers(texture, seen & inside)
    seconds["lighting"] = time.perf_counter() - t0
    hand.mean_texture = np.ascontiguousarray(np.transpose(texture, (2, 0, 1))).astype(np.float32)
    report = _report(hand, fit, views, seen, inside, texture, opt)
    report["texels"]["rejected_fraction"] = round(float(rejected.sum()
                                                        / max(inside.sum(), 1)), 5)
    return Personalized(hand, fit, report, seconds, radiance, seen)


#: A texel whose T̄ luminance lies outside [LOW, HIGH] × the median over the hand is
#: taken as a failed measurement, not skin: where the fitted surface and the photo do
#: not quite register at a shadow's edge, or a shadow the irradiance misplaces, L / E
#: reaches 20 × the median (measured on the stage's scans, bench_personalize.py) while
#: skin albedo varies by a few tens of percent.  Such texels are refilled from the
#: nearest measured one, as unseen texels are.  Measured on template-5's scan (seed 0's
#: universal model, held-out env maps): no rejection 16.9 dB, [0.2, 2.5] 23.5 dB,
#: [0.5, 1.6] 25.6 dB (6.6 % of the texels rejected), [0.7, 1.3] 25.5 dB.  A hand with
#: brighter nails or a tattoo past 1.6 × its median loses them to their surroundings.
LOW, HIGH = 0.5, 1.6


def reject_outliers(texture: np.ndarray, measured: np.ndarray):
    """(texture with outlier and unmeasured texels refilled from the nearest kept texel,
    [N, N] bool the rejected ones)."""
    from scipy.ndimage import distance_transform_edt

    from relight_cli.neural.unwrap import luminance
    y = luminance(texture)
    if not measured.any():
        return texture, np.zeros(measured.shape, bool)
    median = float(np.median(y[measured]))
    rejected = measured & ((y > HIGH * median) | (y < LOW * median))
    kept = measured & ~rejected
    if kept.any() and not kept.all():
        _, (iy, ix) = distance_transform_edt(~kept, return_indices=True)
        texture = texture[iy, ix]
    return texture, rejected


def fitted_hand(template, fit):
    """``template`` (copied) with the fitted bone scales baked into its meshes and the
    pose groups' poses as its frames."""
    from relight_cli.hand.fitting import personalize_mesh
    hand = copy.deepcopy(template)
    for which in ("coarse", "fine"):
        m = hand.mesh(which)
        m.vertices = personalize_mesh(m.vertices, m.weights, template.rest_joints,
                                      template.parents, fit.bone_scales)
    hand.rest_joints = fit.rest_joints
    hand.bone_scales = fit.bone_scales
    hand.hands = hand.hands[:1]
    hand.hands[0].poses = np.asarray(fit.poses, np.float64)
    hand.hands[0].translations = np.asarray(fit.translations, np.float64)
    hand.mean_texture = None
    return hand


def _unwrap(hand, views, env, opt):
    """(radiance [N, N, 3], irradiance [N, N, 3] or None, weight [N, N], inside [N, N]):
    the views' cosine-weighted mean radiance per texel (holes filled from the nearest seen
    texel) and, with ``env``, the same average of each view's irradiance."""
    from relight_cli.bake import pose_scene
    from relight_cli.neural.geometry import PoseTexels
    from relight_cli.neural.unwrap import Accumulator, env_irradiance, view_samples
    from relight_cli.uvraster import rasterize_uv

    n = opt.tex_res
    acc, acc_e = Accumulator(1, n), Accumulator(1, n)
    denv = None
    if env is not None and opt.lighting == "env":
        from relight_cli.envmap import discretize_env
        denv = discretize_env(env, *opt.env_res)
    raster, inside = None, None
    for g in sorted({v.pose for v in views}):
        meshes = pose_scene(hand, g, "fine")
        if raster is None:
            raster = rasterize_uv(meshes[0].uv, meshes[0].faces_uv, n)
        texels = PoseTexels(meshes, n, [raster])
        if inside is None:
            inside = texels.inside(0)
        e = None if denv is None else env_irradiance(texels, 0, denv)
        for v in views:
            if v.pose != g:
                continue
            samples = view_samples(texels, 0, v.camera, v.image, v.mask)
            acc.add(0, samples)
            if e is not None and samples is not None:
                rr, cc, _, cos = samples
                acc_e.add(0, (rr, cc, e[rr, cc], cos))
    weight = acc.weight[0]
    if not (weight > 0).any():
        raise ValueError("no texel of the fitted hand is seen inside any mask")
    return (acc.mean(0), None if denv is None else acc_e.mean(0), weight, inside)


def _statistical(radiance, seen, views, opt):
    from relight_cli.neural.unwrap import luminance, shading_map
    pixels = np.concatenate([v.image[v.mask] for v in views])
    reference = pixels.mean(0)
    shading = shading_map(radiance, seen, reference, opt.tv_weight)
    texture = radiance / shading[..., None]
    level = opt.level
    current = float(luminance(texture[seen]).mean()) if seen.any() else 0.0
    if level is not None and current > 0:
        texture = texture * (level / current)
    return texture


def _report(hand, fit, views, seen, inside, texture, opt) -> dict:
    from relight_cli.hand.fitting import bone_lengths
    names = hand.joint_names
    lengths = bone_lengths(fit.rest_joints[None], np.ones((1, len(names)), bool),
                           hand.parents)[0]
    covered = float((seen & inside).sum() / max(inside.sum(), 1))
    return {
        "views": [{"image": v.name, "pose": int(v.pose),
                   "reprojection_px": round(float(e), 3),
                   "outside_mask_px": None if not np.isfinite(o) else round(float(o), 3)}
                  for v, e, o in zip(views, fit.reprojection_px, fit.outside_px)],
        "bone_scales": {names[j]: round(float(fit.bone_scales[j]), 5)
                        for j in range(1, len(names))},
        "bone_lengths_mm": {names[j]: round(float(lengths[j]), 3) for j in range(1, len(names))},
        "texels": {"resolution": opt.tex_res, "inside": int(inside.sum()),
                   "seen_fraction": round(covered, 5)},
        "lighting": opt.lighting,
        "mean_texture_mean": [round(float(c), 6) for c in texture[inside].mean(0)],
    }
