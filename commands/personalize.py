"""``relight personalize``: a relightable subject (hand.npz + mean texture) from photos."""

from __future__ import annotations

import os

import click

from relight_cli.cli.tools import (check_input, check_output, dumps_json, log,
                                   no_clobber_option, quiet_option, seed_option)


@click.command("personalize",
               short_help="A new hand from a few photos: fitted hand.npz + its mean texture.")
@click.argument("images", nargs=-1, required=True, metavar="IMAGE...")
@click.option("-o", "--output", required=True, metavar="SUBJECT.npz",
              help="The subject: the fitted hand.npz carrying its mean texture T̄ "
                   "(formats/hand_npz.md), for relight … --model linear.")
@click.option("--cameras", required=True, metavar="RIG.json",
              help="One relight/camera per image, in the order of the images "
                   "(formats/camera.md).")
@click.option("--keypoints", required=True, metavar="KP2D.json",
              help="2D keypoints per image from any detector, webxr-25 or mediapipe-21 "
                   "(formats/keypoints2d.md); views sharing a 'pose' id share a hand pose.")
@click.option("--masks", default=None, metavar="PATTERN",
              help="Foreground masks, a pattern with {stem} (the image's name without its "
                   "extension), e.g. 'masks/{stem}.png'; white = hand. Default: each "
                   "image's alpha channel.")
@click.option("--env", default=None, metavar="ENV",
              help="The scan's lighting (an env map file or builtin:NAME): T̄ = radiance / "
                   "irradiance, exact for diffuse skin. Without it, the shading is "
                   "estimated (URHand supp. 9) and T̄'s level taken from --checkpoint.")
@click.option("--checkpoint", default=None, metavar="CKPT.pt",
              help="The universal linear model: sets --tex-res, and without --env the level "
                   "of T̄ (its trained subjects' mean brightness).")
@click.option("--template", default=None, metavar="builtin:right|builtin:left|HAND.npz",
              help="The hand to fit [default: the built-in hand of the keypoints' side, "
                   "else of --hand].")
@click.option("--hand", "side", type=click.Choice(["right", "left"]), default=None,
              help="Which hand the photos show when the keypoints file does not say "
                   "[default: right].")
@click.option("--tex-res", type=click.IntRange(4, 4096), default=None, metavar="N",
              help="Side of T̄ (a power of two) [default: the checkpoint's, else 256].")
@click.option("--iterations", type=click.IntRange(1, 100_000), default=200, show_default=True,
              help="Iterations of the 3D fit to the triangulated keypoints (its pose-only "
                   "stage runs a third), then of the refinement on the images.")
@click.option("--colour-space", "colour_space", type=click.Choice(["auto", "srgb", "linear"]),
              default="auto", show_default=True,
              help="Of the images: auto = EXR linear, PNG/JPEG/TIFF 8-bit sRGB.")
@click.option("--report", default=None, metavar="FIT.json",
              help="Per-view reprojection error, bone scales and lengths, texel coverage "
                   "('-' for stdout).")
@click.option("--preview", default=None, metavar="PNG",
              help="A sheet: the photos with the fitted joints, T̄ and its coverage.")
@seed_option
@no_clobber_option
@quiet_option
def command(images, output, cameras, keypoints, masks, env, checkpoint, template, side, tex_res,
            iterations, colour_space, report, preview, seed, no_clobber, quiet):
    """Personalise the universal hand model from a few photos of a new hand
    (URHand Sec. 5.4, supp. 9): fit the hand's pose and bone lengths to 2D
    keypoints and masks, unwrap the photos into the UV layout (visibility- and
    angle-weighted, holes filled), divide the scan's lighting out, and write the
    fitted hand.npz with its mean texture T̄.  Render the person with
    `relight SUBJECT.npz ENV --model linear --checkpoint UNIVERSAL.pt`.

    \b
    Examples:
      relight synth-capture builtin:right --phone-scan builtin:studio -o scan/
      relight personalize scan/view_*.exr --cameras scan/cameras.json \\
          --keypoints scan/keypoints.json --env builtin:studio -o me.npz
      relight personalize photos/*.jpg --cameras rig.json --keypoints kp.json \\
          --masks 'photos/mask_{stem}.png' --checkpoint universal.pt -o me.npz
    """
    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.formats.hand_npz import FORMAT, VERSION, write_hand
    from relight_cli.jobs import personalize as job
    from relight_cli.provenance import provenance

    check_output(output, no_clobber, kind="npz")
    check_output(report, no_clobber, kind="json", what="--report")
    check_output(preview, no_clobber, kind="png", what="--preview")
    if masks is not None and "{stem}" not in masks:
        raise UsageProblem("--masks is a pattern with {stem}, e.g. 'masks/{stem}.png'")
    if tex_res is not None and tex_res & (tex_res - 1):
        raise UsageProblem(f"--tex-res must be a power of two, got {tex_res}")
    if len(set(map(os.path.basename, images))) != len(images):
        raise UsageProblem("two images share a file name (the keypoints name views by it)")
    for path in (*images, cameras, keypoints):
        check_input(path)

    from relight_cli.formats.camera import read_cameras
    from relight_cli.formats.keypoints2d import read_keypoints2d
    rig = read_cameras(cameras)
    if len(rig) != len(images):
        raise DataError(f"{len(images)} image(s) but {len(rig)} camera(s); give one camera "
                        f"per image, in the images' order", cameras)
    kp = read_keypoints2d(keypoints)
    order = _match_views(images, kp, keypoints)
    level, model_res, inputs = None, None, {}
    if checkpoint is not None:
        level, model_res = _checkpoint_level(checkpoint)
        inputs["checkpoint"] = checkpoint
    if env is None and level is None:
        raise UsageProblem("give --env (the scan's lighting) or --checkpoint (the universal "
                           "model, which sets the level of an estimated T̄)")
    res = tex_res or model_res or 256
    views = [_read_view(path, rig[i], kp, order[i], masks, colour_space)
             for i, path in enumerate(images)]
    side = kp.side or side or "right"
    template = template or f"builtin:{side}"
    from relight_cli.cli.inputs import load_envmap, load_template
    template_hand = load_template(template)
    if template_hand.side != side:
        raise UsageProblem(f"the photos show a {side} hand but --template {template} is a "
                           f"{template_hand.side} hand")
    lighting = None if env is None else load_envmap(env)
    uv = kp.uv[order]
    conf = kp.confidence[order]
    for i, v in enumerate(views):
        _check_keypoints(v, uv[i], conf[i], keypoints)

    say = (lambda message: log(message, quiet))
    say(f"personalize: {len(views)} photo(s), {len(set(v.pose for v in views))} pose(s), "
        f"{kp.skeleton} keypoints, template {template}, T̄ {res}², lighting "
        f"{'env ' + env if env else 'estimated (supp. 9)'}")
    options = job.PersonalizeOptions(tex_res=res, iterations=iterations,
                                     lighting="env" if env else "statistical", level=level,
                                     seed=seed)
    bar = _StageBar(quiet)
    try:
        result = job.personalize(template_hand, views, uv, conf, lighting, options, bar)
    except ValueError as exc:
        raise DataError(str(exc), keypoints) from None
    finally:
        bar.close()
    r = result.report
    mean_px = sum(v["reprojection_px"] for v in r["views"]) / len(r["views"])
    say(f"fit: mean reprojection {mean_px:.2f} px, {r['texels']['seen_fraction']:.0%} of the "
        f"texels seen; fit {result.seconds['fit']:.1f} s, unwrap "
        f"{result.seconds['unwrap']:.1f} s, lighting {result.seconds['lighting']:.1f} s")

    inputs.update({f"image{i}": p for i, p in enumerate(images)})
    inputs.update({"cameras": cameras, "keypoints": keypoints})
    if env is not None and not env.startswith("builtin:"):
        inputs["env"] = env
    settings = {"template": template, "tex_res": res, "iterations": iterations,
                "lighting": options.lighting, "env": env, "masks": masks,
                "colour_space": colour_space, "seed": seed}
    write_hand(output, result.hand, provenance(FORMAT, VERSION, inputs, settings))
    log(f"wrote {output}: the fitted hand and its mean texture ({res}²)", quiet)
    if report is not None:
        from relight_cli.fileio import write_text_atomic
        write_text_atomic(report, dumps_json({
            "format": "relight/personalize-report", "version": 1, **r,
            "provenance": provenance("relight/personalize-report", 1, inputs, settings)}))
    if preview is not None:
        _write_preview(preview, views, result, uv, conf)
        log(f"wrote {preview}", quiet)


def _match_views(images, kp, path) -> list:
    """For each image, the index of the keypoint view naming it (by file name)."""
    from relight_cli.errors import DataError
    names = {name: i for i, name in enumerate(kp.images)}
    order = []
    for image in images:
        base = os.path.basename(image)
        if base not in names:
            raise DataError(f"no keypoints for image {base!r} (views name "
                            f"{', '.join(kp.images[:3])}{', …' if len(kp.images) > 3 else ''})",
                            path)
        order.append(names[base])
    return order


def _checkpoint_level(path: str):
    """(mean luminance of the trained subjects' T̄, the model's tex_res) of a linear
    checkpoint."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    from relight_cli.neural.unwrap import luminance
    check_input(path)
    ckpt = read_checkpoint(path)
    try:
        model = load_hand_model(ckpt, "cpu", name=path)
    except ValueError as exc:
        raise DataError(str(exc), path) from None
    if model.mean_texture is None or model.kind != "linear":
        raise DataError("not a linear-model checkpoint (relight train-teacher --model linear)",
                        path)
    textures = [t for _, _, t in model.subjects] or [model.mean_texture]
    levels = [float(luminance(np.transpose(t[0].cpu().numpy(), (1, 2, 0))).mean())
              for t in textures]
    return float(np.mean(levels)), model.tex_res


def _read_view(path, camera, kp, index, masks, colour_space):
    """A :class:`ScanView` (linear RGB, bool mask) checked against its camera."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.formats.image import read_image
    from relight_cli.jobs.personalize import ScanView
    pixels, names = read_image(path)
    h, w = pixels.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise DataError(f"image is {w}×{h} but its camera {camera.name or ''} is "
                        f"{camera.width}×{camera.height}", path)
    if not np.isfinite(pixels).all():
        raise DataError("image holds NaN/Inf", path)
    upper = [n.upper() for n in names]
    colour = [upper.index(c) for c in "RGB"] if all(c in upper for c in "RGB") else None
    if colour is None:
        if pixels.shape[2] in (1, 2):
            colour = [0, 0, 0]
        else:
            colour = [0, 1, 2]
    rgb = pixels[..., colour].astype(np.float64)
    exr = path.lower().endswith(".exr")
    if colour_space == "srgb" or (colour_space == "auto" and not exr):
        from relight_cli.formats.gaussians_ply import srgb_eotf
        rgb = srgb_eotf(np.clip(rgb, 0.0, 1.0))
    if masks is not None:
        stem = os.path.splitext(os.path.basename(path))[0]
        mask_path = masks.replace("{stem}", stem)
        check_input(mask_path)
        m, _ = read_image(mask_path)
        if m.shape[:2] != (h, w):
            raise DataError(f"mask is {m.shape[1]}×{m.shape[0]} but its image is {w}×{h}",
                            mask_path)
        mask = m[..., 0] > 0.5
        where = mask_path
    elif "A" in upper:
        mask = pixels[..., upper.index("A")] > 0.5
        where = path
    else:
        raise DataError("image has no alpha channel; give --masks", path)
    if not mask.any():
        raise DataError("empty mask: no pixel is marked as hand", where)
    return ScanView(os.path.basename(path), camera, rgb, mask, int(kp.pose[index]))


def _check_keypoints(view, uv, conf, path) -> None:
    """Keypoints (confidence > 0) must lie inside their image."""
    import numpy as np

    from relight_cli.errors import DataError
    cam = view.camera
    seen = conf > 0
    out = seen & ((uv[:, 0] < -0.5) | (uv[:, 0] > cam.width - 0.5) | (uv[:, 1] < -0.5)
                  | (uv[:, 1] > cam.height - 0.5))
    if out.any():
        j = int(np.nonzero(out)[0][0])
        raise DataError(f"view {view.name}: keypoint {j} at ({uv[j, 0]:.1f}, {uv[j, 1]:.1f}) "
                        f"lies outside the {cam.width}×{cam.height} image", path)


class _StageBar:
    """A progress bar per fitting stage (callable(stage, step, total))."""

    def __init__(self, quiet: bool):
        self.quiet, self.stage, self.bar = quiet, None, None

    def __call__(self, stage, step, total):
        from relight_cli.cli.tools import progress
        if stage != self.stage:
            self.close()
            self.stage, self.bar = stage, progress(total=total, desc=stage, quiet=self.quiet)
        self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _write_preview(path, views, result, uv, conf) -> None:
    """Up to four photos with the detected (green) and fitted (red) joints, then T̄ (× π:
    a white Lambertian surface shows white) and the texels the photos saw."""
    import math

    import numpy as np

    from relight_cli.hand.skinning import posed_joints
    from relight_cli.preview import Tile, expose, write_sheet
    hand, fit = result.hand, result.fit
    joints = posed_joints(fit.poses, fit.translations, fit.rest_joints, hand.parents)
    tiles = []
    white = None
    for i, v in enumerate(views[:4]):
        display, note, white = expose(v.image, white=white)
        display = display.copy()
        cam = v.camera
        x = joints[v.pose] @ np.asarray(cam.R).T + np.asarray(cam.t)
        fitted = x[:, :2] / x[:, 2:] @ np.asarray(cam.K)[:2, :2].T + np.asarray(cam.K)[:2, 2]
        for points, colour, keep in ((uv[i], (0.1, 0.9, 0.1), conf[i] > 0),
                                     (fitted, (0.95, 0.1, 0.1), np.ones(len(fitted), bool))):
            for px, py in points[keep]:
                cx, cy = int(round(px)), int(round(py))
                display[max(cy - 1, 0):cy + 2, max(cx - 1, 0):cx + 2] = colour
        tiles.append(Tile(display, v.name, f"{fit.reprojection_px[i]:.2f} px (green found, "
                                           f"red fit)"))
    texture = np.transpose(hand.mean_texture, (1, 2, 0)) * math.pi
    t_disp, _, _ = expose(texture, mode="unit")
    seen = result.seen.astype(np.float64)
    s_disp, _, _ = expose(seen, mode="unit")
    rows = [tiles, [Tile(t_disp, "mean texture x pi", "0…1 linear"),
                    Tile(s_disp, "texels seen",
                         f"{result.report['texels']['seen_fraction']:.0%} of the hand's")]]
    write_sheet(path, rows, "relight personalize")
