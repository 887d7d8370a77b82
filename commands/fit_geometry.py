"""``relight fit-geometry``: write a posed hand (hand.npz), or fit one to keypoints and scans."""

from __future__ import annotations

import click

from relight_cli.cli.tools import (FiniteFloat, check_input, check_output, dumps_json, log,
                                   no_clobber_option, parse_size, quiet_option, renamed_option,
                                   seed_option)
from relight_cli.sequence import parse_frames


@click.command("fit-geometry", short_help="Pose or fit the articulated hand; write hand.npz.")
@click.option("-o", "--output", required=True, help="Output hand.npz.")
@click.option("--template", default="builtin:right", show_default=True,
              help="builtin:right, builtin:left, a skinned glTF/GLB hand, or a hand.npz. "
                   "Not given: the built-in hand of the tracked side (--hand left, or a "
                   "recording of a left hand, takes builtin:left).")
@click.option("--pose", default=None,
              help="Without targets: a named pose (open relaxed fist point pinch ok spread claw), "
                   "'random', or a JSON file of poses. Default: relaxed.")
@click.option("--n-frames", "n_frames", type=int, default=1, show_default=True,
              help="Number of frames to make for --pose random.")
@click.option("--keypoints", default=None,
              help="3D keypoints to fit: JSON or .npy, (N, 25, 3) or (N, 25, 4) with confidence "
                   "(0 = missing), metres, template joint order (formats/keypoints.md).")
@click.option("--keypoints-format", type=click.Choice(["auto", "keypoints", "leap"]),
              default="auto", show_default=True,
              help="Reader of --keypoints: relight/keypoints, a Leap Motion recording (LeapJS "
                   "JSON, formats/leap.md), or auto (Leap when the JSON holds Leap frames).")
@click.option("--hand", "hand_choice", default=None, metavar="left|right|both|ID",
              help="The hand to fit: by type, or a Leap hand id (default: a Leap recording's "
                   "type present in most frames; both hands of a keypoints file with a "
                   "'hands' list). both: the left and the right hand in one two-hand "
                   "hand.npz (one skeleton, the other hand its mirror image). Frames "
                   "without the hand are missing, not filled unless --interpolate.")
@click.option("--frames", "frame_range", default=None, metavar="all|A:B[:S]",
              help="Fit only the keypoint frames numbered A, A+S, … below B (the frame "
                   "grammar of every command: a Python slice, e.g. 0:300:10) [default: all].")
@renamed_option("--frame-range", "--frames", why="one frame grammar in every command")
@click.option("--scans", default=None,
              help="Scan meshes to fit (PLY/OBJ/STL), one per frame in sorted order; a glob "
                   "pattern like 'scan_*.ply' (quote it).")
@click.option("--interpolate", is_flag=True,
              help="Fill the frames between fitted keyframes (keypoint 'frames' numbers) by "
                   "quaternion slerp.")
@click.option("--iterations", type=int, default=300, show_default=True,
              help="Optimizer iterations of the joint stage (a pose-only stage runs a third).")
@click.option("--no-bone-scales", is_flag=True, help="Keep bone lengths of the template.")
@click.option("--offsets", is_flag=True,
              help="Also fit per-vertex offsets (Laplacian-regularized; needs --scans).")
@click.option("--smooth", type=FiniteFloat(0, 1e6), default=0.0, show_default=True,
              help="Weight of temporal smoothness between consecutive frames.")
@click.option("--two-hands", is_flag=True,
              help="Add the mirrored other hand beside the first one (for two-hand scenes).")
@click.option("--report", default=None,
              help="Write a JSON report of per-frame residuals (MPJPE, scan distance in mm); "
                   "'-' for stdout.")
@click.option("--preview", default=None, help="Also write a tone-mapped PNG of frame 0.")
@click.option("--preview-size", default="320x320", show_default=True,
              help="Preview size WxH (or N for NxN).")
@seed_option
@no_clobber_option
@quiet_option
def command(output, template, pose, n_frames, keypoints, keypoints_format, hand_choice,
            frame_range, scans, interpolate, iterations, no_bone_scales, offsets, smooth,
            two_hands, report, preview, preview_size, seed, no_clobber, quiet):
    """Write the articulated hand as hand.npz: posed (--pose) or fitted to 3D
    keypoints and/or scan meshes (--keypoints, --scans).

    Fitting estimates per-frame pose and translation plus shared per-bone
    length scales (and optional per-vertex offsets) with a robust loss,
    joint-limit priors and optional temporal smoothness.

    \b
    Examples:
      relight fit-geometry --pose fist -o hand.npz --preview hand.png
      relight fit-geometry --pose random --n-frames 10 --seed 3 -o poses.npz
      relight fit-geometry --template hand.glb --keypoints kp.npy -o fit.npz --report fit.json
      relight fit-geometry --keypoints kp.json --scans 'scan_*.ply' --offsets -o fit.npz
      relight fit-geometry --keypoints pinch.json --hand right --frames 0:300:10 \
          --interpolate -o pinch.npz --report pinch_fit.json   # a Leap Motion recording
      relight fit-geometry --keypoints claps.json --hand both --interpolate -o two.npz
    """
    from relight_cli.cli import inputs as I
    from relight_cli.formats.hand_npz import FORMAT, VERSION, write_hand
    from relight_cli.jobs import fit_geometry as job
    from relight_cli.provenance import provenance

    size = _check_usage(output, pose, n_frames, keypoints, keypoints_format, hand_choice,
                        frame_range, scans, interpolate, iterations, offsets, report, preview,
                        preview_size, no_clobber, two_hands)
    leap_hand = "both" if hand_choice == "both" else I.leap_hand(hand_choice)
    frame_slice = None if frame_range is None else \
        parse_frames(frame_range, "--frames", count_option="--n-frames").as_slice()
    scan_paths = None if scans is None else I.scan_paths(scans)
    if keypoints is not None:
        check_input(keypoints)

    # ---- inputs, then the job (its log lines come once every input has been read)
    from relight_cli.cli.tools import given_options
    chosen = "template" in given_options(click.get_current_context())
    if not chosen and hand_choice in ("left", "right"):
        template = f"builtin:{hand_choice}"      # --hand left: the left built-in hand
    template_hand = I.load_template(template)
    inputs = {} if template.startswith("builtin:") else {"template": template}
    settings = {"template": template, "seed": seed, "two_hands": two_hands}
    say = (lambda message: log(message, quiet))
    if keypoints is None and scans is None:
        poses, trans = I.load_poses(pose or "relaxed", n_frames, seed, template_hand)
        fitted = job.pose(template_hand, poses, trans, two_hands, template, log=say)
        settings["pose"] = pose or "relaxed"
        if pose is not None and pose.endswith(".json"):
            inputs["pose"] = pose
    elif _two_hands_wanted(keypoints, keypoints_format, leap_hand):
        kps = [I.load_keypoints(keypoints, template_hand, keypoints_format, side, frame_slice,
                                side_follows=True)
               for side in (template_hand.side, _other(template_hand.side))]
        options = job.FitGeometryOptions(iterations, not no_bone_scales, False, smooth,
                                         interpolate, seed)
        fitted = job.fit_hands(template_hand, kps, options, log=say, quiet=quiet,
                               names={"template": template, "keypoints": keypoints})
        inputs["keypoints"] = keypoints
        settings.update(keypoints_format=keypoints_format, frame_range=frame_range,
                        hand="both")
    else:
        kp = None if keypoints is None else I.load_keypoints(
            keypoints, template_hand, keypoints_format, leap_hand, frame_slice,
            side_follows=not chosen)
        if kp is not None and kp.side not in (None, template_hand.side):
            # the tracked hand is the other one and --template was not given: its built-in
            template = f"builtin:{kp.side}"
            template_hand = I.load_template(template)
            settings["template"] = template
            say(f"note: the tracked hand is a {kp.side} hand: template {template}")
        points = None if scan_paths is None else I.load_scans(scan_paths, seed)
        options = job.FitGeometryOptions(iterations, not no_bone_scales, offsets, smooth,
                                         interpolate, seed, two_hands)
        fitted = job.fit(template_hand, kp, points, options, log=say, quiet=quiet,
                         names={"template": template, "keypoints": keypoints,
                                "scan": (scan_paths or [None])[0]})
        if keypoints is not None:
            inputs["keypoints"] = keypoints
            settings.update(keypoints_format=keypoints_format, frame_range=frame_range,
                            hand=None if leap_hand is None else str(leap_hand))
        for i, p in enumerate(scan_paths or []):
            inputs[f"scan{i}"] = p
    settings.update(fitted.settings)

    # ---- outputs
    hand = fitted.hand
    write_hand(output, hand, provenance(FORMAT, VERSION, inputs, settings))
    log(f"wrote {output}: {len(hand.hands)} hand(s), {hand.n_frames} frame(s)", quiet)
    if report is not None:
        from relight_cli.fileio import write_text_atomic
        write_text_atomic(report, dumps_json({
            "format": "relight/fit-report", "version": 1, **fitted.report,
            "provenance": provenance("relight/fit-report", 1, inputs, settings)}))
    if preview is not None:
        _write_preview(preview, hand, size, output)
        log(f"wrote {preview}", quiet)


def _other(side: str) -> str:
    return "left" if side == "right" else "right"


def _two_hands_wanted(keypoints, keypoints_format, leap_hand) -> bool:
    """``--hand both``, or no --hand and a keypoints file whose 'hands' list holds two."""
    if leap_hand == "both":
        return True
    if leap_hand is not None or keypoints is None or keypoints_format == "leap":
        return False
    from relight_cli.formats.keypoints import keypoint_sides
    return len(keypoint_sides(keypoints) or ()) == 2


def _check_usage(output, pose, n_frames, keypoints, keypoints_format, hand_choice, frame_range,
                 scans, interpolate, iterations, offsets, report, preview, preview_size,
                 no_clobber, two_hands=False):
    """The options' usage errors (exit 2), before any work; the preview size (W, H)."""
    from relight_cli.errors import UsageProblem

    if output == "-":
        raise UsageProblem("hand.npz is binary and cannot go to stdout; give a file name")
    check_output(output, no_clobber, kind="npz")
    check_output(report, no_clobber, kind="json", what="--report")
    size = None
    if preview is not None:
        check_output(preview, no_clobber, kind="png", what="--preview")
        size = parse_size(preview_size, "--preview-size")
    fitting = keypoints is not None or scans is not None
    if fitting and pose is not None:
        raise UsageProblem("--pose poses the template; it cannot be combined with "
                           "--keypoints/--scans")
    if not 1 <= n_frames <= 100_000:
        raise UsageProblem(f"--n-frames must be in [1, 100000], got {n_frames}")
    if n_frames != 1 and pose != "random":
        raise UsageProblem("--n-frames applies to --pose random only")
    if not 1 <= iterations <= 1_000_000:
        raise UsageProblem(f"--iterations must be in [1, 1000000], got {iterations}")
    if offsets and scans is None:
        raise UsageProblem("--offsets needs --scans (keypoints alone cannot see the surface)")
    if interpolate and keypoints is None:
        raise UsageProblem("--interpolate needs --keypoints with frame numbers")
    if keypoints is None and (hand_choice is not None or frame_range is not None
                              or keypoints_format != "auto"):
        raise UsageProblem("--hand, --frames and --keypoints-format need --keypoints")
    if frame_range is not None:
        parse_frames(frame_range, "--frames", count_option="--n-frames")
    if frame_range is not None and scans is not None:
        raise UsageProblem("--frames selects keypoint frames; it cannot be combined "
                           "with --scans (one scan per keypoint frame)")
    if hand_choice == "both" and (scans is not None or two_hands):
        raise UsageProblem("--hand both fits two hands to keypoints; it cannot be combined "
                           "with --scans or --two-hands")
    return size


def _write_preview(path, hand, size, output) -> None:
    """A tone-mapped, labelled PNG of frame 0 (fine mesh, shaded)."""
    import os

    from relight_cli.hand.scene import posed_meshes, preview_camera, render_preview
    from relight_cli.preview import write_preview
    meshes = posed_meshes(hand, 0, "fine")
    image = render_preview(meshes, preview_camera(meshes, *size))
    write_preview(path, image, exposure=2.0,
                  label=f"{os.path.basename(output)}, frame 0: {len(hand.hands)} hand(s)",
                  note="fine mesh, shaded")
