"""Scene light estimation from Gaussians (paper Sec. 3.1): ``--lights auto:K``.

Dominant point lights are found among the scene's own Gaussians.  Two named
variants; ``paper`` (default) follows Sec. 3.1, ``v1`` is this toolkit's first
reading (kept for comparison):

1. Region of interest: Gaussians within ``roi_radius`` of ``roi_center`` — the
   paper centres it on the character's alpha-weighted centroid (the avatar is
   an input: ``character=``), else the scene's own centroid; no radius = all.
2. Photometric cues from multi-view SH evaluation: each Gaussian's colour is
   evaluated from V viewpoints (3DGS colour 0.5 + Σ sh Y(d), d from the
   viewpoint to the Gaussian).  ``paper``: the viewpoints lie "near the
   character", on a sphere of the character's radius around its centroid
   (``v1``: a quarter of the ROI's diagonal around the ROI centre).  With
   luminance Y = 0.2126 R + 0.7152 G + 0.0722 B over the views: mean Ȳ, max Ŷ,
   angular stability s = 1 − std/mean ∈ [0, 1] (emitters look alike from
   everywhere), DC dominance δ = |f_dc|² / Σ|f|² (1 for degree 0).
3. Soft clipping of extreme outliers (``paper``): Ȳ and Ŷ above the fence
   q = 10·Q99 (an order of magnitude beyond the bulk of the scene) are
   compressed to q·(1 + tanh((Y − q)/q)) < 2q, so one blown-out floater cannot
   swamp the scores (order kept; real lamps sit below the fence).  ``v1``: none.
4. Base score b = opacity · (Ȳ + Ŷ)/2 · (½ + ½s) · (½ + ½δ) — no size term,
   so no bias toward large Gaussians.  Only the high-score tail (the
   ``candidates`` best) goes on.
5. Peakness (local contrast) favours compact emitters over bright extended
   surfaces: p = b / (score of the k nearest neighbours) — their average
   (``paper``: "compared against the average score in a small spatial
   neighborhood") or median (``v1``); final score b · p/(1 + p).
6. Greedy distance NMS: take the best, suppress all within ``nms_radius``,
   repeat until K lights.  Position = the winner's centre.
7. Colour (unit luminance): ``paper`` — its SH evaluated toward the character
   (viewed from the character's centroid); ``v1`` — its mean multi-view colour.
   Intensity: ``paper`` — its base score b; ``v1`` — its mean luminance Ȳ.

Everything is deterministic (no sampling), so identical inputs give identical lights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relight_cli.formats.gaussians_ply import Gaussians
from relight_cli.formats.lights_json import Lights
from relight_cli.sh import sh_basis

LUMA = np.array([0.2126, 0.7152, 0.0722])
VARIANTS = ("paper", "v1")


@dataclass
class LightEstimate:
    """K estimated point lights and the estimator's diagnostics.

    Attributes:
        lights: the lights, a ``formats.lights_json.Lights``: positions [K, 3] (metres,
            world), colors [K, 3] (linear RGB with unit luminance), intensities [K]
            (``paper``: the base score b of the emitting Gaussian; ``v1``: its mean
            luminance, scene units); no names, no extra fields.
        scores: [K] final scores (base · peakness factor), descending.
        indices: [K] indices of the chosen Gaussians in the input.
    """

    lights: Lights
    scores: np.ndarray
    indices: np.ndarray


CLIP_FACTOR = 10.0   # the soft-clip fence, in multiples of the 99th percentile


def soft_clip(values: np.ndarray) -> np.ndarray:
    """Compress values above the fence q = CLIP_FACTOR·Q99 smoothly, q·(1 + tanh((v − q)/q)).

    An order of magnitude above the bulk of the scene a lamp keeps its value
    (lamps are rare but rarely 10× brighter than the 99th percentile of an HDR
    capture's Gaussians); a blown-out floater of 1e4 is pulled below 2q.
    Monotonic, so the order of candidates is kept.
    """
    v = np.asarray(values, np.float64)
    if len(v) < 10:
        return v.copy()
    fence = CLIP_FACTOR * float(np.percentile(v, 99))
    if not fence > 0:
        return v.copy()
    over = v > fence
    out = v.copy()
    out[over] = fence * (1 + np.tanh((v[over] - fence) / fence))
    return out


def photometric_cues(g: Gaussians, center, view_radius: float, n_views: int = 16,
                     clip_outliers: bool = False) -> dict:
    """Per-Gaussian cues from ``n_views`` viewpoints on a sphere around ``center``.

    ``clip_outliers``: soft-clip mean and max luminance (:func:`soft_clip`) before
    the base score.  Returns a dict of [N] arrays ``mean_luminance``,
    ``max_luminance`` (unclipped), ``stability``, ``dc_dominance``, ``base`` and
    [N, 3] ``mean_color``.
    """
    from .probe import fibonacci_sphere
    views = np.asarray(center, np.float64) + view_radius * fibonacci_sphere(n_views)   # [V, 3]
    n = len(g)
    lum_sum = np.zeros(n)
    lum_sq = np.zeros(n)
    lum_max = np.zeros(n)
    color_sum = np.zeros((n, 3))
    for v in views:
        d = g.means - v
        if g.sh_degree == 0:
            col = g.colors()
        else:
            col = np.maximum(0.5 + np.einsum("nk,nkc->nc", sh_basis(d, g.sh_degree), g.sh), 0.0)
        y = col @ LUMA
        lum_sum += y
        lum_sq += y * y
        lum_max = np.maximum(lum_max, y)
        color_sum += col
    mean = lum_sum / n_views
    std = np.sqrt(np.maximum(lum_sq / n_views - mean ** 2, 0.0))
    stability = np.clip(1.0 - std / np.maximum(mean, 1e-12), 0.0, 1.0)
    energy = (g.sh ** 2).sum(axis=(1, 2))
    dc = (g.sh[:, 0] ** 2).sum(axis=1)
    dc_dominance = np.where(energy > 0, dc / np.where(energy > 0, energy, 1.0), 1.0)
    m, mx = (soft_clip(mean), soft_clip(lum_max)) if clip_outliers else (mean, lum_max)
    base = g.opacities * 0.5 * (m + mx) * (0.5 + 0.5 * stability) * (0.5 + 0.5 * dc_dominance)
    return {"mean_luminance": mean, "max_luminance": lum_max, "stability": stability,
            "dc_dominance": dc_dominance, "base": base, "mean_color": color_sum / n_views}


def colour_toward(g: Gaussians, index, viewpoint) -> np.ndarray:
    """[K, 3] 3DGS colours of Gaussians ``index`` seen from ``viewpoint`` [3] (clamped ≥ 0)."""
    idx = np.asarray(index, np.int64)
    if g.sh_degree == 0:
        return g.colors()[idx]
    d = g.means[idx] - np.asarray(viewpoint, np.float64)
    return np.maximum(0.5 + np.einsum("nk,nkc->nc", sh_basis(d, g.sh_degree), g.sh[idx]), 0.0)


def estimate_lights(g: Gaussians, count: int, roi_center=None, roi_radius: float | None = None,
                    n_views: int = 16, neighbours: int = 32, candidates: int = 2048,
                    nms_radius: float | None = None, character: Gaussians | None = None,
                    variant: str = "paper") -> LightEstimate:
    """Estimate ``count`` point lights from scene Gaussians (see the module docstring).

    Args:
        g: scene Gaussians (world frame).
        count: K ≥ 1.
        roi_center: [3] centre of interest (default: the character's alpha-weighted
            centroid when ``character`` is given, else the scene's).
        roi_radius: only Gaussians within this distance (default: all).
        n_views: viewpoints for the multi-view SH cues.
        neighbours: k of the local-contrast neighbourhood.
        candidates: the high-score tail: how many top base scores enter the
            peakness/NMS stage.
        nms_radius: suppression distance (default: 10% of the ROI's bounding-box diagonal).
        character: the avatar (occluder) Gaussians, or None.
        variant: ``paper`` or ``v1`` (module doc).

    Returns:
        :class:`LightEstimate`: at most ``count`` lights (fewer if the ROI is smaller) and
        their scores and Gaussian indices.

    Raises:
        ValueError: no Gaussians in the ROI, count < 1, or an unknown variant.
    """
    from scipy.spatial import cKDTree

    if count < 1:
        raise ValueError("the number of lights must be at least 1")
    if variant not in VARIANTS:
        raise ValueError(f"light estimator must be one of {VARIANTS}, got {variant!r}")
    paper = variant == "paper"
    if character is not None and len(character):
        w = character.opacities
        char_centre = (w[:, None] * character.means).sum(0) / max(w.sum(), 1e-300)
        char_radius = float(np.percentile(np.linalg.norm(character.means - char_centre, axis=1), 95))
    else:
        char_centre, char_radius = None, None
    centroid = (g.opacities[:, None] * g.means).sum(0) / max(g.opacities.sum(), 1e-300)
    if roi_center is not None:
        center = np.asarray(roi_center, np.float64)
    elif char_centre is not None:
        center = char_centre
    else:
        center = centroid
    idx = np.arange(len(g))
    if roi_radius is not None:
        idx = idx[np.linalg.norm(g.means - center, axis=1) <= roi_radius]
    if len(idx) == 0:
        raise ValueError("no scene Gaussians inside the light-estimation region")
    sub = g.subset(idx)
    lo, hi = sub.means.min(0), sub.means.max(0)
    diagonal = float(np.linalg.norm(hi - lo))
    if nms_radius is None:
        nms_radius = 0.1 * diagonal
    if paper and char_centre is not None:
        view_centre, view_radius = char_centre, max(char_radius, 1e-3)   # near the character
    else:
        view_centre, view_radius = center, max(0.25 * diagonal, 1e-3)
    cues = photometric_cues(sub, view_centre, view_radius, n_views, clip_outliers=paper)
    base = cues["base"]
    tree = cKDTree(sub.means)
    top = np.argsort(-base, kind="stable")[:min(candidates, len(sub))]
    k = int(min(neighbours + 1, len(sub)))
    _, nb = tree.query(sub.means[top], k=k)
    nb = nb.reshape(len(top), k)[:, 1:] if k > 1 else nb.reshape(len(top), 1)
    local = np.mean(base[nb], axis=1) if paper else np.median(base[nb], axis=1)
    peak = base[top] / np.maximum(local, 1e-12 * max(base.max(), 1e-300))
    score = base[top] * peak / (1.0 + peak)
    order = np.argsort(-score, kind="stable")
    chosen = []
    for j in order:
        p = sub.means[top[j]]
        if all(np.linalg.norm(p - sub.means[top[c]]) > nms_radius for c in chosen):
            chosen.append(j)
            if len(chosen) == count:
                break
    sel = top[np.array(chosen, dtype=np.int64)]
    if paper:
        col = colour_toward(sub, sel, view_centre)          # the SH toward the character
        intensity = base[sel].copy()
    else:
        col = cues["mean_color"][sel]
        intensity = cues["mean_luminance"][sel].copy()
    lum = np.maximum(col @ LUMA, 1e-12)
    return LightEstimate(Lights(sub.means[sel].copy(), col / lum[:, None], intensity),
                         scores=score[np.array(chosen, dtype=np.int64)], indices=idx[sel])


def parse_auto(spec: str) -> int | None:
    """``auto:K`` → K (None for anything else); K must be a positive integer."""
    if not spec.startswith("auto:"):
        return None
    try:
        k = int(spec[5:])
    except ValueError:
        raise ValueError(f"expected auto:K with an integer K, got {spec!r}") from None
    if k < 1:
        raise ValueError(f"auto:K needs K ≥ 1, got {spec!r}")
    return k
