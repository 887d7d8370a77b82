"""``relight fit-geometry``: write a posed hand (hand.npz), or fit one to keypoints and scans."""

from __future__ import annotations

import click

from relight_cli.clitools import (FiniteFloat, check_input, check_output, dumps_json, log,
                                  no_clobber_option, parse_size, quiet_option, seed_option)


@click.command("fit-geometry", short_help="Pose or fit the articulated hand; write hand.npz.")
@click.option("-o", "--output", required=True, help="Output hand.npz.")
@click.option("--template", default="builtin:right", show_default=True,
              help="builtin:right, builtin:left, a skinned glTF/GLB hand, or a hand.npz.")
@click.option("--pose", default=None,
              help="Without targets: a named pose (open relaxed fist point pinch ok spread claw), "
                   "'random', or a JSON file of poses. Default: relaxed.")
@click.option("--frames", type=int, default=1, show_default=True,
              help="Number of frames for --pose random.")
@click.option("--keypoints", default=None,
              help="3D keypoints to fit: JSON or .npy, (N, 25, 3) or (N, 25, 4) with confidence "
                   "(0 = missing), metres, template joint order (formats/keypoints.md).")
@click.option("--keypoints-format", type=click.Choice(["auto", "keypoints", "leap"]),
              default="auto", show_default=True,
              help="Reader of --keypoints: relight/keypoints, a Leap Motion recording (LeapJS "
                   "JSON, formats/leap.md), or auto (Leap when the JSON holds Leap frames).")
@click.option("--hand", "hand_choice", default=None, metavar="left|right|ID",
              help="Leap: the hand to fit, by type or Leap hand id (default: the type present "
                   "in most frames). Frames without it are missing, not filled unless "
                   "--interpolate.")
@click.option("--frame-range", default=None, metavar="START:STOP[:STEP]",
              help="Fit only the keypoint frames numbered START, START+STEP, … below STOP "
                   "(Python slice; e.g. 0:300:10).")
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
def command(output, template, pose, frames, keypoints, keypoints_format, hand_choice,
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
      relight fit-geometry --pose random --frames 10 --seed 3 -o poses.npz
      relight fit-geometry --template hand.glb --keypoints kp.npy -o fit.npz --report fit.json
      relight fit-geometry --keypoints kp.json --scans 'scan_*.ply' --offsets -o fit.npz
      relight fit-geometry --keypoints pinch.json --hand right --frame-range 0:300:10 \
          --interpolate -o pinch.npz --report pinch_fit.json   # a Leap Motion recording
    """
    import glob as globmod

    from relight_cli.errors import UsageProblem

    if output == "-":
        raise UsageProblem("hand.npz is binary and cannot go to stdout; give a file name")
    check_output(output, no_clobber, kind="npz")
    check_output(report, no_clobber, kind="json", what="--report")
    if preview is not None:
        check_output(preview, no_clobber, kind="png", what="--preview")
        size = parse_size(preview_size, "--preview-size")
    fitting = keypoints is not None or scans is not None
    if fitting and pose is not None:
        raise UsageProblem("--pose poses the template; it cannot be combined with "
                           "--keypoints/--scans")
    if not 1 <= frames <= 100_000:
        raise UsageProblem(f"--frames must be in [1, 100000], got {frames}")
    if frames != 1 and pose != "random":
        raise UsageProblem("--frames applies to --pose random only")
    if not 1 <= iterations <= 1_000_000:
        raise UsageProblem(f"--iterations must be in [1, 1000000], got {iterations}")
    if offsets and scans is None:
        raise UsageProblem("--offsets needs --scans (keypoints alone cannot see the surface)")
    if interpolate and keypoints is None:
        raise UsageProblem("--interpolate needs --keypoints with frame numbers")
    if keypoints is None and (hand_choice is not None or frame_range is not None
                              or keypoints_format != "auto"):
        raise UsageProblem("--hand, --frame-range and --keypoints-format need --keypoints")
    if frame_range is not None and scans is not None:
        raise UsageProblem("--frame-range selects keypoint frames; it cannot be combined "
                           "with --scans (one scan per keypoint frame)")
    if keypoints_format == "keypoints" and hand_choice is not None:
        raise UsageProblem("--hand applies to Leap recordings only")
    from relight_cli.formats.leap import parse_hand_choice
    try:
        hand_choice = parse_hand_choice(hand_choice)
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None
    frame_slice = None if frame_range is None else _parse_frame_range(frame_range)
    scan_paths = None
    if scans is not None:
        scan_paths = sorted(globmod.glob(scans)) if any(c in scans for c in "*?[") else [scans]
        if not scan_paths:
            raise UsageProblem(f"--scans {scans!r} matches no files")
        for p in scan_paths:
            check_input(p)
    if keypoints is not None:
        check_input(keypoints)

    from relight_cli.formats.hand_npz import FORMAT, VERSION, write_hand
    from relight_cli.provenance import provenance

    hand = _load_template(template)
    # Logged only once every input has been read: a bad input gets one line only.
    template_line = (f"template {template}: {hand.side} hand, coarse {len(hand.coarse.vertices)}"
                     f" / fine {len(hand.fine.vertices)} vertices")
    inputs = {} if template.startswith("builtin:") else {"template": template}
    settings = {"template": template, "seed": seed, "two_hands": two_hands}
    report_obj = None
    if not fitting:
        poses, trans = _poses_for(pose or "relaxed", frames, seed, hand)
        log(template_line, quiet)
        hand.hands[0].poses, hand.hands[0].translations = poses, trans
        settings.update(pose=pose or "relaxed", frames=int(len(poses)))
        if pose is not None and pose.endswith(".json"):
            inputs["pose"] = pose
    else:
        reader = dict(reader=keypoints_format, hand=hand_choice, frames=frame_slice)
        hand, report_obj = _fit(hand, keypoints, reader, scan_paths, interpolate, iterations,
                                not no_bone_scales, offsets, smooth, seed, quiet, template_line)
        if keypoints is not None:
            inputs["keypoints"] = keypoints
            settings.update(keypoints_format=keypoints_format, frame_range=frame_range,
                            hand=None if hand_choice is None else str(hand_choice))
        for i, p in enumerate(scan_paths or []):
            inputs[f"scan{i}"] = p
        settings.update(iterations=iterations, bone_scales=not no_bone_scales,
                        offsets=offsets, smooth=smooth, interpolate=interpolate)
    if two_hands:
        from relight_cli.hand.scene import two_hands as add_other
        hand = add_other(hand)
    write_hand(output, hand, provenance(FORMAT, VERSION, inputs, settings))
    log(f"wrote {output}: {len(hand.hands)} hand(s), {hand.n_frames} frame(s)", quiet)
    if report is not None:
        from relight_cli.provenance import write_text_atomic
        if report_obj is None:
            report_obj = {"frames": hand.n_frames, "fitted": False}
        report_obj = {"format": "relight/fit-report", "version": 1, **report_obj,
                      "provenance": provenance("relight/fit-report", 1, inputs, settings)}
        write_text_atomic(report, dumps_json(report_obj))
    if preview is not None:
        import os

        from relight_cli.preview import write_preview
        from relight_cli.hand.scene import posed_meshes, preview_camera, render_preview
        meshes = posed_meshes(hand, 0, "fine")
        camera = preview_camera(meshes, *size)
        image = render_preview(meshes, camera)
        write_preview(preview, image, exposure=2.0,
                      label=f"{os.path.basename(output)}, frame 0: {len(hand.hands)} hand(s)",
                      note="fine mesh, shaded")
        log(f"wrote {preview}", quiet)


def _load_template(spec: str):
    from relight_cli.errors import DataError, UsageProblem

    if spec.startswith("builtin:"):
        side = spec.split(":", 1)[1]
        if side not in ("right", "left"):
            raise UsageProblem(f"unknown built-in template {spec!r}; use builtin:right or "
                               "builtin:left")
        from relight_cli.hand.model import builtin_hand
        return builtin_hand(side, pose=None)
    check_input(spec)
    lower = spec.lower()
    if lower.endswith((".glb", ".gltf")):
        from relight_cli.formats.hand_npz import validate
        from relight_cli.hand.gltf import import_gltf
        hand = import_gltf(spec)
        validate(hand, spec)   # degenerate geometry is refused now, naming the glTF
        return hand
    if lower.endswith(".npz"):
        import numpy as np

        from relight_cli.formats.hand_npz import read_hand
        hand = read_hand(spec)
        hand.hands = hand.hands[:1]
        hand.hands[0].poses = np.zeros((1,) + hand.hands[0].poses.shape[1:])
        hand.hands[0].translations = np.zeros((1, 3))
        return hand
    raise DataError("unknown template type (expected builtin:right|left, .glb/.gltf or .npz)",
                    spec)


def _poses_for(pose: str, frames: int, seed: int, hand):
    import numpy as np

    from relight_cli.errors import DataError, UsageProblem
    from relight_cli.hand import poses as P

    J = hand.n_joints
    rest = hand.rest_joints
    if pose == "random":
        p = P.random_poses(frames, seed=seed, side=hand.side, rest_joints=rest)
        return p, np.zeros((frames, 3))
    if pose in P.POSE_NAMES:
        return P.named_pose(pose, hand.side, rest)[None], np.zeros((1, 3))
    if pose.endswith(".json"):
        from relight_cli.formats._common import read_json
        check_input(pose)
        obj = read_json(pose)
        if isinstance(obj, dict) and "names" in obj:
            try:
                p = np.stack([P.named_pose(n, hand.side, rest) for n in obj["names"]])
            except (KeyError, TypeError) as exc:
                raise DataError(f"bad pose name: {exc}", pose) from None
            if len(p) == 0:
                raise DataError("'names' is empty", pose)
            return p, np.zeros((len(p), 3))
        poses_list = obj.get("poses") if isinstance(obj, dict) else obj
        try:
            p = np.asarray(poses_list, np.float64)
            t = (np.asarray(obj["translations"], np.float64)
                 if isinstance(obj, dict) and "translations" in obj else np.zeros((len(p), 3)))
        except (TypeError, ValueError):
            raise DataError("'poses' must be an N × J × 3 array of numbers", pose) from None
        if p.ndim == 2:
            p = p[None]
        if p.ndim != 3 or p.shape[1:] != (J, 3) or len(p) == 0:
            raise DataError(f"'poses' must have shape (N, {J}, 3) axis-angle, got {p.shape}", pose)
        if t.shape != (len(p), 3):
            raise DataError(f"'translations' must have shape ({len(p)}, 3), got {t.shape}", pose)
        if not (np.isfinite(p).all() and np.isfinite(t).all()):
            raise DataError("poses or translations hold NaN/Inf", pose)
        return p, t
    raise UsageProblem(f"--pose must be one of {', '.join(P.POSE_NAMES)}, 'random' or a "
                       f".json file, got {pose!r}")


def _read_scan(path: str, rng):
    """Points [P, 3] sampled on a scan mesh (or its vertices for point clouds)."""
    import numpy as np
    import trimesh

    from relight_cli.errors import DataError

    try:
        geom = trimesh.load(path, force=None, process=False)
    except Exception as exc:  # trimesh raises many types for damaged files
        raise DataError(f"unreadable scan: {type(exc).__name__}: {exc}", path) from None
    if isinstance(geom, trimesh.Scene):
        geom = geom.dump(concatenate=True) if geom.geometry else None
    if geom is None:
        raise DataError("scan is empty", path)
    if isinstance(geom, trimesh.Trimesh) and len(geom.faces):
        if geom.area <= 0:
            raise DataError("scan mesh has zero area", path)
        pts, _ = trimesh.sample.sample_surface(geom, 5000, seed=int(rng.integers(2**31)))
    else:
        pts = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))))
    pts = np.asarray(pts, np.float64)
    if len(pts) < 10:
        raise DataError(f"scan has only {len(pts)} points", path)
    if not np.isfinite(pts).all():
        raise DataError("scan holds NaN/Inf coordinates", path)
    return pts


def _parse_frame_range(text: str) -> slice:
    from relight_cli.errors import UsageProblem
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        start, stop, step = (int(p) if p.strip() else None for p in parts + [""] * (3 - len(parts)))
    except ValueError:
        raise UsageProblem(f"--frame-range must be START:STOP[:STEP] with integers, got "
                           f"{text!r}") from None
    if (start or 0) < 0 or (stop is not None and stop < 0) or (step is not None and step < 1):
        raise UsageProblem(f"--frame-range takes frame numbers ≥ 0 and STEP ≥ 1, got {text!r}")
    return slice(start, stop, step)


def _read_targets(path: str, n_joints: int, side: str, reader: dict):
    """Keypoints of ``path`` (relight/keypoints or Leap), checked against the template's
    handedness and cut to --frame-range."""
    import numpy as np

    from relight_cli.errors import DataError
    from relight_cli.formats.keypoints import read_keypoints

    kp = read_keypoints(path, n_joints, reader["reader"], reader["hand"])
    if reader["hand"] is not None and kp.source is None:
        from relight_cli.errors import UsageProblem
        raise UsageProblem("--hand applies to Leap recordings only")
    if kp.side is not None and kp.side != side:
        raise DataError(f"the tracked hand is a {kp.side} hand but the template is a {side} "
                        f"hand; use --template builtin:{kp.side} (or --hand)", path)
    cut = reader["frames"]
    if cut is not None:
        f = kp.frames
        start, step = cut.start or 0, cut.step or 1
        keep = (f >= start) & ((f - start) % step == 0)
        if cut.stop is not None:
            keep &= f < cut.stop
        if not keep.any():
            raise DataError(f"no keypoint frames in --frame-range {start}:"
                            f"{'' if cut.stop is None else cut.stop}:{step} (the file has "
                            f"frames {f[0]}…{f[-1]})", path)
        kp.positions, kp.confidence, kp.frames = \
            kp.positions[keep], kp.confidence[keep], kp.frames[keep]
    return kp


def _fit(hand, keypoints, reader, scan_paths, interpolate, iterations, bone_scales, offsets,
         smooth, seed, quiet, template_line):
    import numpy as np

    from relight_cli.clitools import progress
    from relight_cli.errors import DataError
    from relight_cli.hand.fitting import FitOptions, fit, fit_quality, personalize_mesh
    from relight_cli.hand.poses import interpolate_poses

    rng = np.random.default_rng(seed)
    kp = None
    if keypoints is not None:
        kp = _read_targets(keypoints, hand.n_joints, hand.side, reader)
    skipped = []
    if kp is not None:
        empty = ~(kp.confidence > 0).any(axis=1)
        if empty.all():
            raise DataError("no selected keypoint frame measures any joint (every confidence "
                            "is 0): nothing to fit", keypoints)
        if empty.any() and scan_paths is not None:
            raise DataError(f"keypoint frame {int(kp.frames[empty][0])} measures no joint "
                            f"(every confidence is 0); with --scans every frame needs "
                            f"keypoints", keypoints)
        if empty.any():   # a frame without any measured joint is a missing frame
            skipped = [int(f) for f in kp.frames[empty]]
            kp.positions, kp.confidence, kp.frames = \
                kp.positions[~empty], kp.confidence[~empty], kp.frames[~empty]
    scans = None
    if scan_paths is not None:
        scans = [_read_scan(p, rng) for p in scan_paths]
        if kp is not None and len(scans) != len(kp.positions):
            raise DataError(f"{len(scans)} scans for {len(kp.positions)} keypoint frames; "
                            "give one scan per frame", scan_paths[0])
    n = len(kp.positions) if kp is not None else len(scans)
    from relight_cli.clitools import log
    log(template_line, quiet)
    if kp is not None and kp.source is not None:
        src = kp.source
        log(f"Leap recording: {src['hand']} hand (id {', '.join(map(str, src['hand_ids']))}) in "
            f"{src['recorded_frames'] - src['frames_without_hand']} of {src['recorded_frames']} "
            f"frames; missing joints (never measured): "
            f"{', '.join(src['never_observed_joints']) or 'none'}", quiet)
    if skipped:
        shown = ", ".join(map(str, skipped[:8])) + (", …" if len(skipped) > 8 else "")
        log(f"skipping {len(skipped)} keypoint frame(s) that measure no joint (frame "
            f"{shown}): " + ("--interpolate fills them" if interpolate else
                             "missing from the output; --interpolate fills them"), quiet)
    log(f"fitting {n} frame(s)" + (f" to {keypoints}" if keypoints else "")
        + (f" and {len(scans)} scan(s)" if scans else ""), quiet)
    bar = progress(total=n, desc="fit frames", quiet=quiet)
    state = {"done": 0}

    def on_progress(stage, step, total):
        # Frames are optimized jointly; advance the frame bar with the joint stage.
        if stage == "fit":
            target = int(n * step / total)
            bar.update(target - state["done"])
            state["done"] = target

    options = FitOptions(iterations=iterations, fit_bone_scales=bone_scales, fit_offsets=offsets,
                         w_smooth=smooth, seed=seed)
    result = fit(hand, None if kp is None else kp.positions,
                 None if kp is None else kp.confidence, scans, options, progress=on_progress)
    bar.close()
    # Bake the personalization into the template.
    parents = hand.parents
    for which in ("coarse", "fine"):
        m = hand.mesh(which)
        off = result.offsets if (which == "coarse" and result.offsets is not None) else None
        if which == "fine" and result.offsets is not None:
            off = _transfer_offsets(hand.coarse, hand.fine, result.offsets)
        m.vertices = personalize_mesh(m.vertices, m.weights, hand.rest_joints, parents,
                                      result.bone_scales, off)
    hand.rest_joints = result.rest_joints
    hand.bone_scales = result.bone_scales
    poses, trans = result.poses, result.translations
    frame_ids = kp.frames if kp is not None else np.arange(n)
    if interpolate and len(frame_ids) > 1:
        all_frames = np.arange(frame_ids[0], frame_ids[-1] + 1)
        poses, trans = interpolate_poses(frame_ids, poses, trans, all_frames)
        out_frames = all_frames
    else:
        out_frames = frame_ids
    hand.hands = hand.hands[:1]
    hand.hands[0].poses, hand.hands[0].translations = poses, trans
    per_frame = []
    for i in range(n):
        row = {"frame": int(frame_ids[i])}
        if kp is not None:
            row["mpjpe_mm"] = _num(result.joint_error_mm[i])
            row["median_joint_error_mm"] = _num(result.joint_median_mm[i])
            row["observed_joints"] = int((kp.confidence[i] > 0).sum())
        if result.scan_mm is not None:
            row["scan_mm"] = _num(result.scan_mm[i])
        per_frame.append(row)
    report = {
        "fitted_frames": n,
        "output_frames": [int(f) for f in out_frames],
        "bone_scales": {name: float(s) for name, s in zip(hand.joint_names, result.bone_scales)},
        "per_frame": per_frame,
    }
    if kp is not None:
        report["frames_without_joints"] = skipped
        report["mpjpe_mm"] = _num(np.nanmean(result.joint_error_mm))
        if kp.source is not None:
            report["keypoints"] = kp.source
        report.update(fit_quality(result, kp.positions, kp.confidence, hand.parents,
                                  hand.joint_names))
    if result.scan_mm is not None:
        report["scan_mm"] = _num(np.mean(result.scan_mm))
    return hand, report


def _num(x):
    import math
    x = float(x)
    return None if math.isnan(x) else round(x, 4)


def _transfer_offsets(coarse, fine, offsets):
    """Coarse-vertex offsets [Vc, 3] carried to the fine mesh by nearest coarse vertex."""
    from scipy.spatial import cKDTree
    _, idx = cKDTree(coarse.vertices).query(fine.vertices)
    return offsets[idx]
