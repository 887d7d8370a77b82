"""``relight metrics image``: MSE, PSNR, SSIM, MAE (and LPIPS) of images, per channel and
masked; one pair or a batch matched by name (:mod:`relight_cli.jobs.metrics`)."""

from __future__ import annotations

import click

from relight_cli.cli import metrics as metrics_io
from relight_cli.cli.tools import (FiniteFloat, check_input, check_output, log, no_clobber_option,
                                   quiet_option)

@click.command("image", short_help="MSE, PSNR, SSIM, MAE of images (per channel, masked).")
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
@metrics_io.output_option
@metrics_io.jsonl_option
@metrics_io.percentiles_option
@no_clobber_option
@quiet_option
def command(pred, gt, mask, whole_image, space, exposure, data_range, win_size, use_lpips,
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

    metrics_io.check_outputs(output, jsonl, no_clobber)
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
                   multi=len(pairs) > 1 or metrics_io.is_multi(pred))
    metrics_io.write_scores(output, jsonl, scores)
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
                                 metrics_io.progress_over(pairs, "image pairs", quiet)):
        g, names, alpha = metrics_io.read_rgb_alpha(g_path)
        p, _ = metrics_io.read_rgb(p_path)
        same_size(p.shape, g.shape, p_path)
        if p.shape[-1] != g.shape[-1]:
            raise DataError(f"has {p.shape[-1]} channel(s), the ground truth has {g.shape[-1]}",
                            p_path)
        region, mask_source = None, None
        if masks[name] is not None:
            region, mask_source = metrics_io.read_mask(masks[name], g.shape), "file"
        elif alpha is not None and not whole_image:
            region, mask_source = metrics_io.alpha_mask(alpha, g_path), "alpha"
        yield ImagePair(name, p, g, names, region, mask_source, p_path, g_path, masks[name])
