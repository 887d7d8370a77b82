"""``relight metrics``: image, shadow and lighting-consistency metrics, and the CI gate.

Subcommands ``image``, ``shadow``, ``lighting`` write a ``relight/metrics`` JSON
record (spec: formats/metrics_json.md); ``compare`` checks one against a baseline
and exits with :data:`EXIT_REGRESSION` when something regressed.  The scoring is
:mod:`relight_cli.jobs.metrics`; this module reads the files and writes the records.
"""

from __future__ import annotations

import click

from relight_cli.clitools import (FiniteFloat, check_input, check_output, log, no_clobber_option,
                                  quiet_option, seed_option)

EXIT_REGRESSION = 3  # `relight metrics compare`: a metric regressed beyond tolerance


@click.group("metrics", short_help="Image, shadow and lighting metrics; compare with a baseline.")
def command():
    """Compute quality metrics as relight/metrics JSON, and gate on them.

    \b
    Exit codes: 0 success, 1 bad data, 2 usage error,
    3 (compare only) a metric regressed beyond its tolerance.
    """


_output = click.option("-o", "--output", default="-", show_default=True,
                       help="Metrics JSON file ('-' for stdout).")
_jsonl = click.option("--jsonl", "jsonl", default=None,
                      help="Also write one JSON row per pair to this file ('-' for stdout).")
_percentiles = click.option("--percentiles", default="5,95", show_default=True,
                            help="Percentiles reported in the batch aggregate.")


# ------------------------------------------------------------------ helpers


def _finite_or_fail(pixels, path):
    import numpy as np

    from relight_cli.errors import DataError
    bad = ~np.isfinite(pixels)
    if bad.any():
        n = int(bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=-1).sum())
        raise DataError(f"{n} pixel(s) hold NaN or Inf values", path)
    return pixels


def _read_rgb(path: str):
    """[H, W, C] float32 colour channels (R, G, B when named so; alpha dropped) and their names."""
    pixels, names, _ = _read_rgb_alpha(path)
    return pixels, names


def _read_rgb_alpha(path: str):
    """(colour channels and their names as :func:`_read_rgb`, the [H, W] float32 alpha
    channel or None): alpha is the channel named ``A`` beside colour channels, as
    OpenImageIO names the alpha of EXR, PNG and TIFF files.  Per-hand coverage
    (``hand0.A``) and a one-channel image are not alpha."""
    from relight_cli.formats.image import read_image
    check_input(path)
    pixels, names = read_image(path)
    alpha = pixels[..., names.index("A")] if "A" in names and len(names) > 1 else None
    if all(c in names for c in "RGB"):
        idx = [names.index(c) for c in "RGB"]
        pixels, names = pixels[..., idx], ["R", "G", "B"]
    elif pixels.shape[-1] == 4:
        pixels, names = pixels[..., :3], names[:3]
    elif pixels.shape[-1] == 2:  # grey + alpha
        pixels, names = pixels[..., :1], names[:1]
    return (_finite_or_fail(pixels, path),
            [n.split(".")[-1] or f"c{i}" for i, n in enumerate(names)], alpha)


def _alpha_mask(alpha, path: str):
    """[H, W] bool foreground (alpha > 0.5) of a ground truth's alpha channel."""
    import numpy as np

    from relight_cli.errors import DataError
    if not np.isfinite(alpha).all():
        raise DataError("the alpha channel holds NaN or Inf values (score every pixel with "
                        "--whole-image)", path)
    mask = alpha > 0.5
    if not mask.any():
        raise DataError("the alpha channel selects no pixels (foreground is alpha > 0.5); "
                        "score every pixel with --whole-image", path)
    return mask


def _read_single(path: str):
    """[H, W] float64 from a one-channel image, its Y/A channel, or Rec. 709 luminance of RGB."""
    import numpy as np

    from relight_cli.formats.image import read_image
    check_input(path)
    pixels, names = read_image(path)
    _finite_or_fail(pixels, path)
    if pixels.shape[-1] == 1:
        return pixels[..., 0].astype(np.float64)
    for name in ("Y", "A"):
        if name in names and not all(c in names for c in "RGB"):
            return pixels[..., names.index(name)].astype(np.float64)
    if all(c in names for c in "RGB"):
        rgb = np.stack([pixels[..., names.index(c)] for c in "RGB"], axis=-1)
    else:
        rgb = pixels[..., :3] if pixels.shape[-1] >= 3 else pixels[..., :1].repeat(3, -1)
    return rgb.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def _read_mask(path: str, shape):
    from relight_cli.errors import DataError
    from relight_cli.jobs.metrics import same_size
    values = _read_single(path)
    same_size(values.shape, shape, path)
    mask = values > 0.5
    if not mask.any():
        raise DataError("mask selects no pixels (foreground is where the mask is > 0.5)", path)
    return mask


def _check_outputs(output, jsonl, no_clobber):
    from relight_cli.errors import UsageProblem
    check_output(output, no_clobber, kind="json")
    if jsonl is not None:
        check_output(jsonl, no_clobber, kind="jsonl", what="--jsonl")
        if jsonl == "-" and output == "-":
            raise UsageProblem("--jsonl - and -o - would both write to stdout; give one a file name")


def _write_scores(output, jsonl, scores):
    """The record of a :class:`relight_cli.jobs.metrics.Scores` (with its provenance) and,
    with --jsonl, one JSON row per pair."""
    from relight_cli.formats.metrics_json import FORMAT, VERSION, write_metrics
    from relight_cli.provenance import provenance, write_text_atomic
    record, rows = scores.record(provenance(FORMAT, VERSION, scores.inputs(), scores.settings))
    if jsonl is not None:
        import json
        write_text_atomic(jsonl, "".join(json.dumps(r, allow_nan=False, ensure_ascii=False) + "\n"
                                         for r in rows))
    write_metrics(output, record)


# ------------------------------------------------------------------ image


@command.command("image", short_help="MSE, PSNR, SSIM, MAE of images (per channel, masked).")
@click.argument("pred", metavar="PRED")
@click.argument("gt", metavar="GT")
@click.option("--mask", default=None,
              help="Foreground mask (> 0.5 = foreground): one file, or a folder/glob matched by "
                   "name [default: the ground truth's alpha channel, when it has one].")
@click.option("--whole-image", "whole_image", is_flag=True,
              help="Score every pixel, also where the ground truth's alpha is background.")
@click.option("--space", type=click.Choice(["linear", "srgb", "display"]), default="linear",
              show_default=True,
              help="linear: HDR values as stored; srgb: both tone-mapped (Reinhard + sRGB) with "
                   "the ground truth's exposure; display: values already in [0, 1] (PNG).")
@click.option("--exposure", type=FiniteFloat(0, min_open=True), default=None,
              help="Exposure multiplier for --space srgb (default: from the ground truth's "
                   "log-average luminance).")
@click.option("--data-range", "data_range", type=FiniteFloat(0, min_open=True), default=None,
              help="Peak-to-peak range R for PSNR/SSIM (default: 1 for srgb/display; "
                   "max−min of the ground truth over the region for linear).")
@click.option("--win-size", "win_size", type=int, default=7, show_default=True,
              help="SSIM window size (odd).")
@click.option("--lpips", "use_lpips", is_flag=True,
              help="Also compute LPIPS (needs --lpips-weights; weights are never downloaded).")
@click.option("--lpips-weights", "lpips_weights", default=None,
              help="Local LPIPS (AlexNet) state dict, see formats/metrics_json.md.")
@click.option("--preview", default=None, metavar="PNG",
              help="One pair only: also write a labelled PNG of the prediction and the ground "
                   "truth on one exposure, and their |difference|, with the scores.")
@_output
@_jsonl
@_percentiles
@no_clobber_option
@quiet_option
def image_command(pred, gt, mask, whole_image, space, exposure, data_range, win_size, use_lpips,
                  lpips_weights, preview, output, jsonl, percentiles, no_clobber, quiet):
    """Compare predicted images PRED with ground truth GT.

    PRED and GT are two image files (EXR, or anything OpenImageIO reads), or two
    folders / glob patterns whose files are matched by name without extension.
    Many pairs give per-pair rows (--jsonl) and mean, median and percentiles.

    Scores are taken inside a mask by default: --mask FILE, else the ground
    truth's alpha channel (> 0.5 = foreground; a capture image's A is its hand
    mask, a render's A its coverage).  A ground truth without alpha is scored
    whole; --whole-image scores every pixel in any case.  The record says which:
    details.region is "mask" or "image", details.pixels the pixels scored.

    \b
    Examples:
      relight metrics image render.exr gt.exr -o m.json            # inside gt.exr's alpha
      relight metrics image render.exr gt.exr --whole-image -o m.json
      relight metrics image render.exr gt.exr --mask fg.png -o m.json
      relight metrics image out/ gt/ --space srgb --jsonl rows.jsonl -o m.json
      relight metrics image 'out/*.exr' gt/ -o -
    """
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.metrics import ImageOptions, image
    from relight_cli.metrics.batch import match_masks, match_pairs, parse_percentiles

    _check_outputs(output, jsonl, no_clobber)
    check_output(preview, no_clobber, kind="png", what="--preview")
    qs = parse_percentiles(percentiles)
    if whole_image and mask is not None:
        raise UsageProblem("--whole-image scores every pixel; it cannot go with --mask")
    if win_size < 3 or win_size % 2 == 0:
        raise UsageProblem(f"--win-size must be odd and at least 3, got {win_size}")
    if exposure is not None and space != "srgb":
        raise UsageProblem("--exposure needs --space srgb")
    if lpips_weights is not None and not use_lpips:
        use_lpips = True
    lpips_net = None
    if use_lpips:
        if lpips_weights is None:
            raise UsageProblem("--lpips needs --lpips-weights FILE (local weights; relight never "
                               "downloads network weights)")
        if space == "linear":
            raise UsageProblem("LPIPS compares display images: add --space srgb or --space display")
        from relight_cli.metrics.lpips import load_lpips
        lpips_net = load_lpips(check_input(lpips_weights))
    pairs, extra = match_pairs(pred, gt)
    if extra:
        log(f"note: {len(extra)} ground-truth file(s) have no prediction and are ignored", quiet)
    if preview is not None and len(pairs) != 1:
        raise UsageProblem(f"--preview shows one pair; PRED and GT matched {len(pairs)}")
    masks = match_masks(mask, [n for n, _, _ in pairs])
    for _, p_path, g_path in pairs:   # every input registered before the first comparison:
        check_input(g_path)           # an output that is one of them is refused first
        check_input(p_path)
    for mask_path in filter(None, masks.values()):
        check_input(mask_path)
    options = ImageOptions(space=space, exposure=exposure, data_range=data_range,
                           win_size=win_size, mask=mask is not None, whole_image=whole_image,
                           percentiles=qs, preview=preview is not None)
    scores = image(_image_pairs(pairs, masks, whole_image, quiet), options, lpips_net,
                   multi=len(pairs) > 1 or _is_multi(pred))
    _write_scores(output, jsonl, scores)
    log(f"{len(scores.results)} pair(s) compared, {scores.note}", quiet)
    if preview is not None:
        from relight_cli.formats.image import write_png
        write_png(preview, scores.preview)
        log(f"wrote {preview}", quiet)


def _image_pairs(pairs, masks, whole_image, quiet):
    """Each matched pair read as a :class:`relight_cli.jobs.metrics.ImagePair` (one at a
    time, so a batch holds one pair in memory): same size and channels, its region from
    the pair's --mask file, else the ground truth's alpha unless --whole-image."""
    from relight_cli.errors import DataError
    from relight_cli.jobs.metrics import ImagePair, same_size

    for name, p_path, g_path in (pairs if len(pairs) < 2 else
                                 _progress(pairs, "image pairs", quiet)):
        g, names, alpha = _read_rgb_alpha(g_path)
        p, _ = _read_rgb(p_path)
        same_size(p.shape, g.shape, p_path)
        if p.shape[-1] != g.shape[-1]:
            raise DataError(f"has {p.shape[-1]} channel(s), the ground truth has {g.shape[-1]}",
                            p_path)
        region, mask_source = None, None
        if masks[name] is not None:
            region, mask_source = _read_mask(masks[name], g.shape), "file"
        elif alpha is not None and not whole_image:
            region, mask_source = _alpha_mask(alpha, g_path), "alpha"
        yield ImagePair(name, p, g, names, region, mask_source, p_path, g_path, masks[name])


def comparison_tiles(pred, gt, region, pred_name="", gt_name=""):
    """``metrics image --preview``'s tiles; kept here for importers: the job's
    :func:`relight_cli.jobs.metrics.comparison_tiles`."""
    from relight_cli.jobs.metrics import comparison_tiles as tiles
    return tiles(pred, gt, region, pred_name, gt_name)


def _is_multi(spec):
    import os

    from relight_cli.metrics.batch import is_glob
    return is_glob(spec) or os.path.isdir(spec)


def _progress(items, desc, quiet):
    from relight_cli.clitools import progress
    return progress(items, total=len(items), desc=desc, quiet=quiet)


# ------------------------------------------------------------------ shadow


def _parse_roi(text):
    from relight_cli.clitools import parse_vector
    from relight_cli.errors import UsageProblem
    if text is None:
        return None
    values = parse_vector(text, 4, "--roi")
    if any(v != int(v) for v in values) or values[2] <= 0 or values[3] <= 0 or min(values[:2]) < 0:
        raise UsageProblem(f"--roi must be X,Y,W,H in whole pixels with W, H > 0, got {text!r}")
    return tuple(int(v) for v in values)


def _avatar_roi(roi, avatar_spec, camera_path, radius, quiet):
    """--roi-avatar: the avatar-centric pixel box (relight_cli.gaussians.shadow_matte.avatar_roi)."""
    import math

    from relight_cli.inputs import load_placed, parse_occluder
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.camera import read_camera
    from relight_cli.gaussians.shadow_matte import avatar_roi

    if roi is not None:
        raise UsageProblem("give --roi or --roi-avatar, not both")
    if camera_path is None:
        raise UsageProblem("--roi-avatar needs --camera CAMERA.json (the mattes' camera)")
    if not (radius > 0 and math.isfinite(radius)):
        raise UsageProblem(f"--roi-radius must be positive, got {radius}")
    source, placement = parse_occluder(avatar_spec, "--roi-avatar")
    check_input(source)
    check_input(camera_path, stdin="--camera")
    avatar = load_placed(source, placement, avatar_spec)
    box = avatar_roi(avatar, read_camera(camera_path), radius)
    if box is None:
        raise DataError("the avatar-centric region is not in the camera's view", avatar_spec)
    log(f"avatar-centric ROI: x {box[0]}, y {box[1]}, {box[2]}x{box[3]} px", quiet)
    return box


@command.command("shadow", short_help="SAE, SM-IoU and boundary F-measure of shadow mattes.")
@click.argument("pred", metavar="PRED")
@click.argument("gt", metavar="GT")
@click.option("--roi", default=None, help="Region of interest X,Y,W,H in pixels (default: all).")
@click.option("--roi-avatar", default=None, metavar="AVATAR",
              help="Compute the ROI from the avatar (paper Sec. 4.2, avatar-centric): the image "
                   "box of the region within --roi-radius (horizontally) of its alpha-weighted "
                   "centroid, floor to top, seen by --camera.  A PLY, mesh or builtin:, with a "
                   "placement SOURCE:KEY=VALUE;... as in dgsm-build.")
@click.option("--camera", "roi_camera", default=None, metavar="CAMERA.json",
              help="The camera of the mattes (for --roi-avatar; '-': stdin).")
@click.option("--roi-radius", type=FiniteFloat(0, 1e6, min_open=True), default=1.0, show_default=True,
              help="Half-size R (metres) of the avatar-centric region.")
@click.option("--threshold", type=FiniteFloat(0, 1, max_open=True), default=0.1, show_default=True,
              help="Matte value above which a pixel counts as shadowed.")
@click.option("--tolerance", type=FiniteFloat(0, 1e4), default=2.0, show_default=True,
              help="Boundary F-measure pixel tolerance.")
@click.option("--matte", type=click.Choice(["shadow", "visibility"]), default="shadow",
              show_default=True, help="What the images hold: shadow strength (1 = full shadow) "
                                      "or visibility (1 = lit; used as 1 − value).")
@_output
@_jsonl
@_percentiles
@no_clobber_option
@quiet_option
def shadow_command(pred, gt, roi, roi_avatar, roi_camera, roi_radius, threshold, tolerance, matte,
                   output, jsonl, percentiles, no_clobber, quiet):
    """Score predicted shadow mattes PRED against pseudo-ground-truth GT (DGSM paper).

    SAE: mean absolute error over the GT shadow region; SM-IoU: IoU of the
    thresholded mattes; boundary F: precision/recall of shadow boundaries within
    --tolerance pixels.  Empty cases are defined (formats/metrics_json.md).
    PRED and GT are files, or folders / globs matched by name.

    \b
    Example:
      relight metrics shadow shadow.exr pseudo_gt.png --threshold 0.1 -o s.json
    """
    from relight_cli.errors import UsageProblem
    from relight_cli.jobs.metrics import ShadowOptions, shadow
    from relight_cli.metrics.batch import match_pairs, parse_percentiles

    _check_outputs(output, jsonl, no_clobber)
    qs = parse_percentiles(percentiles)
    roi_box = _parse_roi(roi)
    if roi_avatar is not None:
        roi_box = _avatar_roi(roi, roi_avatar, roi_camera, roi_radius, quiet)
    elif roi_camera is not None:
        raise UsageProblem("--camera is for --roi-avatar")
    pairs, extra = match_pairs(pred, gt)
    if extra:
        log(f"note: {len(extra)} ground-truth file(s) have no prediction and are ignored", quiet)
    options = ShadowOptions(threshold=threshold, tolerance=tolerance, roi=roi_box, matte=matte,
                            percentiles=qs, roi_avatar=roi_avatar, roi_radius=roi_radius)
    scores = shadow(_shadow_pairs(pairs, quiet), options, multi=len(pairs) > 1 or _is_multi(pred))
    _write_scores(output, jsonl, scores)
    log(f"{len(scores.results)} pair(s) scored", quiet)


def _shadow_pairs(pairs, quiet):
    """Each matched pair of mattes read as a :class:`relight_cli.jobs.metrics.ShadowPair`
    (one at a time); a matte outside [0, 1] (beyond rounding) is bad data."""
    from relight_cli.errors import DataError
    from relight_cli.jobs.metrics import ShadowPair

    for name, p_path, g_path in (pairs if len(pairs) < 2 else
                                 _progress(pairs, "shadow pairs", quiet)):
        mattes = []
        for path in (p_path, g_path):
            values = _read_single(path)
            if values.min() < -1e-3 or values.max() > 1 + 1e-3:
                raise DataError(f"matte values must lie in [0, 1], found "
                                f"[{values.min():.4g}, {values.max():.4g}]", path)
            mattes.append(values)
        yield ShadowPair(name, mattes[0], mattes[1], p_path, g_path)


# ------------------------------------------------------------------ lighting


@command.command("lighting", short_help="PAA-Y, APF-Y, NCM-ab of a Gaussian avatar in a Gaussian scene.")
@click.option("--scene", required=True, help="Scene Gaussians PLY (the environment).")
@click.option("--avatar", "avatars", required=True, multiple=True,
              help="Original avatar Gaussians PLY; repeat for several frames.")
@click.option("--relit", "relits", multiple=True,
              help="Relit avatar PLY per frame (same count as --avatar).")
@click.option("--radius", type=FiniteFloat(0, min_open=True), default=1.5, show_default=True,
              help="Scene Gaussians within this distance (metres) of the avatar centre light it.")
@click.option("--neighbours", type=int, default=16, show_default=True,
              help="Neighbours for the local-PCA pseudo-normals.")
@click.option("--normals", "normal_source", type=click.Choice(["pca", "ply"]), default="pca",
              show_default=True, help="Pseudo-normals by weighted local PCA, or the PLY's nx ny nz.")
@click.option("--max-points", type=int, default=512, show_default=True,
              help="Points per side of the seeded subsamples on which the 2-D Wasserstein "
                   "distance of large sets is solved exactly.")
@_output
@seed_option
@no_clobber_option
@quiet_option
def lighting_command(scene, avatars, relits, radius, neighbours, normal_source, max_points, output,
                     seed, no_clobber, quiet):
    """Lighting consistency of a Gaussian avatar with the scene around it (DGSM paper, Sec. 4.1).

    The paper's metrics: luminance factorized as Y ≈ α·E(n; c), E order-3 SH
    (16 coefficients, |c|₂ = 1 fixing the scale), α ≥ 0 per Gaussian, Huber
    loss and 5 % trimming, for the scene within --radius and for the avatar.
    paa_y = |c_avatar − c_scene|₁; apf_y = mean |Y − (s·E(n; c_scene) + b)|
    after a per-frame affine fit; ncm_ab = exact 1-Wasserstein distance of the
    avatar's and the scene's CIE-Lab (a*, b*) point sets (exact on seeded
    subsamples of --max-points per side for large sets; the JSON says which).
    This toolkit's earlier variants are reported beside them as paa_angle
    (degrees between dominant light directions), apf_rms and ncm_ab_weighted
    (formats/metrics_json.md).  Lower is better for all.  Reports orig, relit
    and relit − orig (delta), averaged over frames.

    \b
    Example:
      relight metrics lighting --scene room.ply --avatar avatar.ply --relit relit.ply \\
          --radius 1.5 -o lighting.json
    """
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.gaussians_ply import read_gaussians
    from relight_cli.formats.metrics_json import FORMAT, VERSION, write_metrics
    from relight_cli.jobs.metrics import LightingOptions, lighting
    from relight_cli.provenance import provenance

    check_output(output, no_clobber, kind="json")
    if relits and len(relits) != len(avatars):
        raise UsageProblem(f"{len(relits)} --relit file(s) for {len(avatars)} --avatar frame(s)")
    if neighbours < 4:
        raise UsageProblem("--neighbours must be at least 4")
    if max_points < 16:
        raise UsageProblem("--max-points must be at least 16")
    scene_g = read_gaussians(check_input(scene))
    frames = []
    for path in list(avatars) + list(relits):
        g = read_gaussians(check_input(path))
        if normal_source == "ply" and g.normals is None:
            raise DataError("PLY has no normals (nx ny nz are absent or all zero); "
                            "use --normals pca", path)
        frames.append(g)
    orig, relit = frames[:len(avatars)], (frames[len(avatars):] or None)
    for path, before, after in zip(relits, orig, relit or []):
        if len(after) != len(before):  # a relit avatar is the same Gaussians, recoloured
            raise DataError(f"has {len(after)} Gaussians, its --avatar has {len(before)}", path)
    options = LightingOptions(radius=radius, neighbours=neighbours,
                              ply_normals=normal_source == "ply", max_points=max_points, seed=seed)
    try:
        scores = lighting(scene_g, orig, relit, options)
    except ValueError as exc:
        raise DataError(str(exc), avatars[0] if "avatar" in str(exc) else scene) from None
    inputs = {"scene": scene}
    for i, path in enumerate(avatars):
        inputs[f"avatar:{i}"] = path
    for i, path in enumerate(relits):
        inputs[f"relit:{i}"] = path
    write_metrics(output, scores.record(provenance(FORMAT, VERSION, inputs, scores.settings)))
    log(f"{len(avatars)} frame(s) scored", quiet)


# ------------------------------------------------------------------ compare


def _parse_keyed(values, what, convert):
    """['psnr=0.01', '0.001', '*.ssim=1e-4'] -> {'psnr': 0.01, None: 0.001, '*.ssim': 1e-4}."""
    from relight_cli.errors import UsageProblem
    out = {}
    for text in values:
        key, sep, value = text.rpartition("=")
        try:
            out[key if sep else None] = convert(value)
        except ValueError:
            raise UsageProblem(f"{what} must look like [METRIC=]VALUE, got {text!r}") from None
    return out


def _tolerance(text):
    value = float(text)
    if not value >= 0 or value == float("inf"):
        raise ValueError(text)
    return value


def _direction(text):
    from relight_cli.metrics.compare import DIRECTIONS
    if text not in DIRECTIONS:
        raise ValueError(text)
    return text


@command.command("compare", short_help="Compare a metrics JSON with a baseline; exit 3 on regression.")
@click.argument("new", metavar="NEW.json")
@click.argument("baseline", metavar="BASELINE.json")
@click.option("--rtol", multiple=True, metavar="[METRIC=]VALUE",
              help="Relative tolerance (default 1e-3), for all metrics or one; repeatable. METRIC "
                   "is a dotted key, a pattern like '*.psnr', or a name like 'psnr'.")
@click.option("--atol", multiple=True, metavar="[METRIC=]VALUE",
              help="Absolute tolerance (default 1e-9); repeatable like --rtol.")
@click.option("--better", multiple=True, metavar="METRIC=higher|lower|either",
              help="Which direction is better (defaults: psnr/ssim/iou/F higher; errors lower; "
                   "unknown metrics: either, so any move beyond tolerance fails).")
@click.option("--only-changed", is_flag=True, help="List only metrics that moved beyond tolerance.")
@click.option("-o", "--output", default=None, metavar="FILE.json|-",
              help="Also write the comparison as JSON (relight/metrics-comparison, "
                   "formats/metrics_json.md), written even when something regressed; with '-' "
                   "it goes to stdout and the table to stderr.")
@click.option("--json", "as_json", is_flag=True,
              help="Write the comparison JSON to stdout (the same as -o -).")
@no_clobber_option
@quiet_option
@click.pass_context
def compare_command(ctx, new, baseline, rtol, atol, better, only_changed, output, as_json,
                    no_clobber, quiet):
    """Compare metrics record NEW.json with BASELINE.json and print what moved.

    Each metric regresses when it moved in its bad direction by more than
    atol + rtol·|baseline|; improvements never fail.  A metric missing from
    NEW.json is a regression.  Either file may be '-' (stdin), not both.

    \b
    Exit codes: 0 nothing regressed, 3 something regressed, 1 unreadable or
    mismatched files, 2 usage error.

    \b
    Examples:
      relight metrics compare new.json baseline.json --rtol 0.01 --rtol psnr=0.002 \\
          --better my_score=higher
      relight metrics image a.exr b.exr -o - | relight metrics compare - base.json -o cmp.json
    """
    from relight_cli.errors import UsageProblem
    from relight_cli.formats.metrics_json import read_metrics
    from relight_cli.jobs.metrics import compare

    if as_json:
        if output not in (None, "-"):
            raise UsageProblem("--json writes the comparison to stdout; it cannot go with -o FILE")
        output = "-"
    check_output(output, no_clobber, kind="json")
    rtols = _parse_keyed(rtol, "--rtol", _tolerance)
    atols = _parse_keyed(atol, "--atol", _tolerance)
    directions = _parse_keyed(better, "--better", _direction)
    if None in directions:
        raise UsageProblem("--better needs METRIC=higher|lower|either")
    check_input(new, stdin="NEW.json")
    check_input(baseline, stdin="BASELINE.json")
    result = compare(read_metrics(new), read_metrics(baseline), rtols, atols, directions,
                     new_name=new, baseline_name=baseline)
    if output is not None:
        _write_comparison(output, result.kind, result.rows, result.regressed, new, baseline,
                          {"rtol": list(rtol), "atol": list(atol), "better": list(better)})
    if not quiet or result.regressed:
        click.echo(result.table(only_changed=only_changed), nl=False, err=output == "-")
    if result.regressed:
        click.echo(f"relight metrics compare: regression against {baseline} "
                   f"(exit {EXIT_REGRESSION})", err=True)
        ctx.exit(EXIT_REGRESSION)


def _write_comparison(output, kind, rows, regressed, new, baseline, given):
    """The relight/metrics-comparison record, landing at once: a regression (exit 3)
    must not discard it as a failed command's outputs are."""
    from relight_cli.clitools import dumps_json
    from relight_cli.formats.metrics_json import (COMPARISON_FORMAT, COMPARISON_VERSION,
                                                  make_comparison)
    from relight_cli.metrics.compare import DEFAULT_ATOL, DEFAULT_RTOL
    from relight_cli.provenance import outside_transaction, provenance, write_text_atomic
    settings = dict(given, default_rtol=DEFAULT_RTOL, default_atol=DEFAULT_ATOL)
    record = provenance(COMPARISON_FORMAT, COMPARISON_VERSION,
                        {"new": new, "baseline": baseline}, settings)
    comparison = make_comparison(kind, [r.to_json() for r in rows],
                                 EXIT_REGRESSION if regressed else 0, record["inputs"], settings,
                                 record)
    with outside_transaction():
        write_text_atomic(output, dumps_json(comparison))
