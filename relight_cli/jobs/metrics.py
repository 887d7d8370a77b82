"""Score images, shadow mattes and lighting, and compare records: ``relight metrics`` as
engine jobs.

Each job takes what the command has read (image arrays, mattes, Gaussians, metrics
records) and an options dataclass, and returns the scores with the settings their
provenance records; building the relight/metrics record needs the provenance (input
hashes), which the caller makes from :meth:`Scores.inputs` and passes to
:meth:`Scores.record`:

    image(pairs, ImageOptions(...))        MSE, PSNR, SSIM, MAE (+ LPIPS) per pair
    shadow(pairs, ShadowOptions(...))      SAE, SM-IoU, boundary F per pair of mattes
    lighting(scene, avatars, relits, LightingOptions(...))   PAA-Y, APF-Y, NCM-ab
    compare(new, baseline, rtols, atols, directions)          the CI gate's rows

    from relight_cli.jobs.metrics import ImageOptions, ImagePair, image
    scores = image([ImagePair("a", pred, gt, ["R", "G", "B"])], ImageOptions())
    scores.results[0][4]["metrics"]["psnr"]

Pairs carry their files' names (``pred_path`` …) as labels only: they key the rows
and records and name the file in an error; nothing is read from them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


# ------------------------------------------------------------------ records


@dataclass
class Scores:
    """Per-pair scores of one kind (``image`` or ``shadow``): ``results`` is
    [(name, pred label, gt label, mask label or None, result dict)]; ``multi``: the
    inputs were folders/globs (a batch record even for one pair); ``details``: the batch
    record's details; ``preview``: the image job's sheet ([H, W, 3] in [0, 1]) or None;
    ``note``: where the scores were taken, in words (for a log line)."""

    kind: str
    results: list
    settings: dict
    multi: bool = False
    percentiles: tuple = (5.0, 95.0)
    details: dict | None = None
    preview: object = None
    note: str = ""

    def inputs(self) -> dict:
        """The record's inputs (label → file), for :func:`relight_cli.provenance.provenance`."""
        single = self._single()
        inputs = {}
        for name, pred, gt, mask, _ in self.results:
            prefix = "" if single else f"{name}:"
            inputs[f"{prefix}pred"] = pred
            inputs[f"{prefix}gt"] = gt
            if mask is not None:
                inputs[f"{prefix}mask"] = mask
        return inputs

    def record(self, prov: dict) -> tuple:
        """(relight/metrics record, its per-pair JSON rows) under provenance ``prov``: one
        pair's scores, or a batch's means, aggregate (mean, median, percentiles) and count."""
        from relight_cli.formats.metrics_json import _encode_tree, make_record
        from relight_cli.metrics.batch import aggregate

        rows = []
        for name, pred, gt, mask, result in self.results:
            row = {"name": name, "pred": pred, "gt": gt}
            if mask is not None:
                row["mask"] = mask
            row.update(result)
            rows.append(_encode_tree(row))
        if self._single():
            result = self.results[0][4]
            details = {k: v for k, v in result.items() if k not in ("metrics", "per_channel")}
            return make_record(self.kind, result["metrics"], prov["inputs"], self.settings, prov,
                               per_channel=result.get("per_channel"),
                               details=details or None), rows
        agg = aggregate([r[4]["metrics"] for r in self.results], self.percentiles)
        means = {k: v["mean"] for k, v in agg.items()}
        return make_record(self.kind, means, prov["inputs"], self.settings, prov, aggregate=agg,
                           pairs=len(self.results), details=self.details), rows

    def _single(self) -> bool:
        return len(self.results) == 1 and not self.multi


def same_size(shape, reference, label, what: str = "ground truth") -> None:
    """DataError naming ``label`` when ``shape`` and ``reference`` differ in H×W."""
    from relight_cli.errors import DataError
    if tuple(shape[:2]) != tuple(reference[:2]):
        raise DataError(f"size {shape[1]}x{shape[0]} differs from the {what}'s "
                        f"{reference[1]}x{reference[0]}", label)


# ------------------------------------------------------------------ image


@dataclass
class ImagePair:
    """One prediction and its ground truth: [H, W, C] float32 arrays of the same size and
    channels (``channels`` their names), ``region`` the [H, W] bool pixels to score (None:
    every pixel), ``mask_source`` where it came from (``file``, ``alpha`` or None)."""

    name: str
    pred: np.ndarray
    gt: np.ndarray
    channels: list
    region: np.ndarray | None = None
    mask_source: str | None = None
    pred_path: str = "pred"
    gt_path: str = "gt"
    mask_path: str | None = None


@dataclass
class ImageOptions:
    """``relight metrics image``'s options: ``space`` linear | srgb | display; ``mask``
    and ``whole_image`` are only recorded (the pairs carry their regions); ``preview``
    makes the one pair's comparison sheet."""

    space: str = "linear"
    exposure: float | None = None
    data_range: float | None = None
    win_size: int = 7
    mask: bool = False
    whole_image: bool = False
    percentiles: tuple = (5.0, 95.0)
    preview: bool = False


def image(pairs, options: ImageOptions, lpips_net=None, multi: bool = False) -> Scores:
    """Score each :class:`ImagePair` of ``pairs`` (any iterable: a reader may yield them
    one at a time); ``lpips_net``: a loaded LPIPS state dict (``--lpips``) or None.
    A pair the engine cannot score (e.g. a constant ground truth in linear space) is a
    DataError naming its mask or ground truth."""
    results, shown = [], None
    for pair in pairs:
        results.append((pair.name, pair.pred_path, pair.gt_path, pair.mask_path,
                        _image_pair(pair, options, lpips_net)))
        shown = pair
    settings = {"space": options.space, "exposure": options.exposure,
                "data_range": options.data_range, "win_size": options.win_size,
                "lpips": lpips_net is not None, "mask": bool(options.mask),
                "whole_image": bool(options.whole_image),
                "percentiles": list(options.percentiles)}
    masked = sum(r[4]["region"] == "mask" for r in results)
    regions = {"region": "mask" if masked == len(results) else "image" if masked == 0 else "mixed",
               "masked_pairs": masked}
    preview = None
    if options.preview and shown is not None:
        preview = comparison_sheet(shown.pred, shown.gt, shown.region, results[-1], options.space)
    return Scores("image", results, settings, multi, options.percentiles, regions, preview,
                  region_note(results))


def _image_pair(pair: ImagePair, options: ImageOptions, lpips_net) -> dict:
    """One pair's result: metrics, per_channel, where they were taken, then the engine's
    details (data range, …), LPIPS and the exposure used."""
    from relight_cli.errors import DataError
    from relight_cli.metrics import image as M

    region = pair.region
    ps, gs, natural, used_exposure = M.to_space(pair.pred, pair.gt, options.space, region,
                                                options.exposure)
    try:
        result = M.image_metrics(ps, gs, region, options.data_range or natural, options.win_size,
                                 pair.channels)
    except ValueError as exc:
        message = str(exc)
        if pair.mask_source == "alpha":
            message = (f"ground truth's alpha: {message} (or score every pixel with "
                       f"--whole-image)")
        raise DataError(message, pair.mask_path or pair.gt_path) from None
    where = {"region": "image" if region is None else "mask"}
    if pair.mask_source is not None:
        where["mask_source"] = pair.mask_source
    where.update(pixels=result.pop("pixels"), image_pixels=int(pair.gt.shape[0] * pair.gt.shape[1]))
    result = {"metrics": result.pop("metrics"), "per_channel": result.pop("per_channel"),
              **where, **result}
    if lpips_net is not None:
        from relight_cli.metrics.lpips import lpips_distance
        result["metrics"]["lpips"] = lpips_distance(lpips_net, ps, gs, result["data_range"],
                                                    region)
    if used_exposure is not None:
        result["exposure"] = used_exposure
    return result


def region_note(results) -> str:
    """Where `metrics image` scored, in words: the mask's source and size, or every pixel."""
    sources = {"alpha": "the ground truth's alpha", "file": "--mask"}
    if len(results) == 1:
        r = results[0][4]
        if r["region"] == "image":
            return f"every pixel ({r['pixels']})"
        return (f"inside {sources[r['mask_source']]} ({r['pixels']} of {r['image_pixels']} "
                f"pixels{'; --whole-image scores all' if r['mask_source'] == 'alpha' else ''})")
    masked = sum(r[4]["region"] == "mask" for r in results)
    return f"{masked} inside a mask, {len(results) - masked} over every pixel"


def comparison_sheet(pred, gt, region, pair, space: str):
    """:func:`comparison_tiles` as a display sheet ([H, W, 3] in [0, 1]) titled with the
    scores (in ``space``) and where they were taken; ``pair`` is the pair's result tuple."""
    from relight_cli.preview import sheet

    name, p_path, g_path, _, result = pair
    m = result["metrics"]
    tiles = comparison_tiles(pred, gt, region, os.path.basename(p_path),
                             os.path.basename(g_path))
    where = ("inside the mask" if result["region"] == "mask" else "every pixel") + \
        f" ({result['pixels']} px)"
    scores = ", ".join(f"{k.upper()} {m[k]:.4g}" for k in ("psnr", "ssim", "mae") if k in m)
    return sheet([tiles], f"metrics image ({space}): {scores}, {where}")


def comparison_tiles(pred, gt, region, pred_name="", gt_name=""):
    """[prediction, ground truth, |difference|] preview tiles of ``metrics image --preview``:
    the pair as stored, on the ground truth's exposure (its 99th percentile inside
    ``region``), the difference on its own."""
    from relight_cli.preview import expose, tile

    colour = (lambda x: x[..., :3]) if gt.shape[-1] >= 3 else (lambda x: x[..., :1])
    _, _, white = expose(colour(gt), "auto", region=region)
    return [tile(colour(pred), f"prediction: {pred_name}", region=region, white=white),
            tile(colour(gt), f"ground truth: {gt_name}", region=region, white=white),
            tile(np.abs(colour(pred) - colour(gt)), "|prediction − ground truth|",
                 region=region, note="own exposure")]


# ------------------------------------------------------------------ shadow


@dataclass
class ShadowPair:
    """A predicted matte and its pseudo ground truth: [H, W] values in [0, 1] (a little
    outside is clipped) holding what ``ShadowOptions.matte`` says."""

    name: str
    pred: np.ndarray
    gt: np.ndarray
    pred_path: str = "pred"
    gt_path: str = "gt"


@dataclass
class ShadowOptions:
    """``relight metrics shadow``'s options: ``roi`` an (x, y, w, h) pixel box or None;
    ``matte`` shadow (1 = full shadow) or visibility (1 = lit); ``roi_avatar`` and
    ``roi_radius`` are only recorded (the caller made ``roi`` from them)."""

    threshold: float = 0.1
    tolerance: float = 2.0
    roi: tuple | None = None
    matte: str = "shadow"
    percentiles: tuple = (5.0, 95.0)
    roi_avatar: str | None = None
    roi_radius: float = 1.0


def shadow(pairs, options: ShadowOptions, multi: bool = False) -> Scores:
    """Score each :class:`ShadowPair` of ``pairs`` (any iterable); a size mismatch is a
    DataError naming the prediction, an impossible ROI a UsageProblem naming the ground
    truth."""
    from relight_cli.errors import UsageProblem
    from relight_cli.metrics.shadow import shadow_metrics

    results = []
    for pair in pairs:
        mattes = [v.clip(0, 1) for v in (pair.pred, pair.gt)]
        if options.matte == "visibility":
            mattes = [1 - v for v in mattes]
        same_size(mattes[0].shape, mattes[1].shape, pair.pred_path)
        try:
            result = shadow_metrics(mattes[0], mattes[1], options.threshold, options.tolerance,
                                    options.roi)
        except ValueError as exc:
            raise UsageProblem(str(exc), pair.gt_path) from None
        results.append((pair.name, pair.pred_path, pair.gt_path, None, result))
    settings = {"threshold": options.threshold, "tolerance": options.tolerance,
                "roi": list(options.roi) if options.roi else None, "matte": options.matte,
                "percentiles": list(options.percentiles), "roi_avatar": options.roi_avatar,
                "roi_radius": options.roi_radius if options.roi_avatar else None}
    return Scores("shadow", results, settings, multi, options.percentiles)


# ------------------------------------------------------------------ lighting


@dataclass
class LightingOptions:
    """``relight metrics lighting``'s options (``ply_normals``: use the PLYs' normals
    instead of local-PCA pseudo-normals)."""

    radius: float = 1.5
    neighbours: int = 16
    ply_normals: bool = False
    max_points: int = 512
    seed: int = 0


@dataclass
class LightingScores:
    """The lighting metrics (orig, relit, delta averaged over frames), per-frame values
    and the settings; :meth:`record` makes the relight/metrics record."""

    metrics: dict
    frames: list
    settings: dict

    def record(self, prov: dict) -> dict:
        from relight_cli.formats.metrics_json import make_record
        return make_record("lighting", self.metrics, prov["inputs"], self.settings, prov,
                           frames=self.frames)


def lighting(scene, avatars, relits, options: LightingOptions) -> LightingScores:
    """Lighting consistency of avatar Gaussians (one set per frame; ``relits`` the same
    Gaussians recoloured, or None) with the ``scene`` Gaussians around them (DGSM paper
    Sec. 4.1).  ValueError from the engine (e.g. no scene Gaussian within the radius)."""
    from relight_cli.metrics.lighting import lighting_metrics

    result = lighting_metrics(scene, list(avatars), list(relits) if relits else None,
                              options.radius, options.neighbours, options.ply_normals,
                              options.max_points, options.seed)
    settings = {"radius": options.radius, "neighbours": options.neighbours,
                "normals": "ply" if options.ply_normals else "pca",
                "max_points": options.max_points, "seed": options.seed, "sh_order": 3,
                "sh_coefficients": 16, "variant_sh_coefficients": 9, "huber": 1.345,
                "trim": 0.05, "scale_fix": "|c|_2 = 1, c_00 > 0",
                "albedo_ridge": 1.0, "factorization_iterations": 6}
    return LightingScores(result["metrics"], result["frames"], settings)


# ------------------------------------------------------------------ compare


@dataclass
class Comparison:
    """The gate's verdict: ``rows`` (:class:`relight_cli.metrics.compare.Row`, one per
    metric), ``regressed`` (any row moved the bad way beyond tolerance) and the
    records' ``kind``."""

    kind: str
    rows: list
    regressed: bool

    def table(self, only_changed: bool = False) -> str:
        from relight_cli.metrics.compare import format_table
        return format_table(self.rows, only_changed=only_changed)


def compare(new: dict, baseline: dict, rtols=None, atols=None, directions=None,
            new_name: str = "new", baseline_name: str = "baseline") -> Comparison:
    """Compare two read relight/metrics records.  ``rtols``/``atols``/``directions`` map a
    metric name or pattern (None: every metric) to a tolerance or a better direction.
    DataError (naming ``new_name``) for records of different kinds, UsageProblem (naming
    ``baseline_name``) for an option naming no metric of either record."""
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.metrics_json import decode_value, flatten
    from relight_cli.metrics.compare import compare_metrics, unknown_names

    rtols, atols, directions = rtols or {}, atols or {}, directions or {}
    if new.get("kind") != baseline.get("kind"):
        raise DataError(f"kind {new.get('kind')!r} differs from the baseline's "
                        f"{baseline.get('kind')!r}", new_name)
    new_leaves = [(k, decode_value(v)) for k, v in flatten(new["metrics"])]
    base_leaves = [(k, decode_value(v)) for k, v in flatten(baseline["metrics"])]
    keys = [k for k, _ in new_leaves + base_leaves]
    for flag, options in (("--rtol", rtols), ("--atol", atols), ("--better", directions)):
        unknown = unknown_names(options, keys)
        if unknown:
            raise UsageProblem(f"{flag} names no metric of these records: {', '.join(unknown)}",
                               baseline_name)
    rows = compare_metrics(new_leaves, base_leaves, rtols, atols, directions)
    return Comparison(new.get("kind"), rows, any(r.regressed for r in rows))
