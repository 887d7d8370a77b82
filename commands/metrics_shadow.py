"""``relight metrics shadow``: SAE, SM-IoU and boundary F-measure of shadow mattes (DGSM
paper Sec. 4.2; :mod:`relight_cli.jobs.metrics`)."""

from __future__ import annotations

import click

from relight_cli.cli import metrics as metrics_io
from relight_cli.cli.tools import FiniteFloat, check_input, log, no_clobber_option, quiet_option

def _parse_roi(text):
    from relight_cli.cli.tools import parse_vector
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

    from relight_cli.cli.inputs import load_placed, parse_occluder
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


@click.command("shadow", short_help="SAE, SM-IoU and boundary F-measure of shadow mattes.")
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
@metrics_io.output_option
@metrics_io.jsonl_option
@metrics_io.percentiles_option
@no_clobber_option
@quiet_option
def command(pred, gt, roi, roi_avatar, roi_camera, roi_radius, threshold, tolerance, matte,
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

    metrics_io.check_outputs(output, jsonl, no_clobber)
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
    scores = shadow(_shadow_pairs(pairs, quiet), options, multi=len(pairs) > 1 or metrics_io.is_multi(pred))
    metrics_io.write_scores(output, jsonl, scores)
    log(f"{len(scores.results)} pair(s) scored", quiet)


def _shadow_pairs(pairs, quiet):
    """Each matched pair of mattes read as a :class:`relight_cli.jobs.metrics.ShadowPair`
    (one at a time); a matte outside [0, 1] (beyond rounding) is bad data."""
    from relight_cli.errors import DataError
    from relight_cli.jobs.metrics import ShadowPair

    for name, p_path, g_path in (pairs if len(pairs) < 2 else
                                 metrics_io.progress_over(pairs, "shadow pairs", quiet)):
        mattes = []
        for path in (p_path, g_path):
            values = metrics_io.read_single(path)
            if values.min() < -1e-3 or values.max() > 1 + 1e-3:
                raise DataError(f"matte values must lie in [0, 1], found "
                                f"[{values.min():.4g}, {values.max():.4g}]", path)
            mattes.append(values)
        yield ShadowPair(name, mattes[0], mattes[1], p_path, g_path)
