"""Pose or fit the articulated hand: ``relight fit-geometry`` as engine jobs.

    pose(template, poses, translations, ...)    the template posed (``--pose``)
    fit(template, keypoints, scans, options)    fitted to 3D keypoints and/or scan points
    fit_hands(template, [kp, kp_other], ...)    both hands of one recording (``--hand both``)

Both take a loaded template (:func:`relight_cli.cli.inputs.load_template`: one hand, rest
frame) and return a :class:`Fitted`: the hand to write (``hand.npz``), the report's
fields and the settings the provenance records.  Inputs come loaded
(:func:`relight_cli.cli.inputs.load_poses`, :func:`~relight_cli.cli.inputs.load_keypoints`,
:func:`~relight_cli.cli.inputs.load_scans`); ``names`` only label them in messages and
errors.  Log lines go to ``log`` (a callable, or None for silence), the frame bar to
:mod:`relight_cli.progress`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class FitGeometryOptions:
    """Fitting options (``relight fit-geometry``'s, same defaults).

    iterations: optimizer iterations of the joint stage (a pose-only stage runs a third).
    bone_scales: fit shared per-bone length scales.  offsets: fit per-vertex offsets
    (needs scans).  smooth: temporal smoothness weight.  interpolate: fill the frames
    between fitted keyframes (keypoint frame numbers) by slerp.  seed: the optimizer's.
    two_hands: add the mirrored other hand beside the result.
    """

    iterations: int = 300
    bone_scales: bool = True
    offsets: bool = False
    smooth: float = 0.0
    interpolate: bool = False
    seed: int = 0
    two_hands: bool = False

    def settings(self) -> dict:
        """What the provenance records of a fit (in this order)."""
        return {"iterations": self.iterations, "bone_scales": self.bone_scales,
                "offsets": self.offsets, "smooth": self.smooth,
                "interpolate": self.interpolate}


@dataclass
class Fitted:
    """A job's result: ``hand`` (HandData: model, per-frame poses, coarse proxy),
    ``report`` (the fit report's fields: per-frame residuals, bone scales; a pose's
    frame count) and ``settings`` (the job's part of the provenance settings)."""

    hand: object
    report: dict
    settings: dict = field(default_factory=dict)


def template_line(template, name: str = "template") -> str:
    """The log line describing a template."""
    return (f"template {name}: {template.side} hand, coarse {len(template.coarse.vertices)}"
            f" / fine {len(template.fine.vertices)} vertices")


def pose(template, poses, translations, two_hands: bool = False, name: str = "template",
         log=None) -> Fitted:
    """``template`` (modified) posed by ``poses`` [N, J, 3] axis-angle and
    ``translations`` [N, 3]; with ``two_hands`` the mirrored other hand added."""
    _log(log, template_line(template, name))
    template.hands[0].poses, template.hands[0].translations = poses, translations
    hand = _with_other(template) if two_hands else template
    return Fitted(hand, {"frames": hand.n_frames, "fitted": False},
                  {"frames": int(len(poses))})


def fit(template, keypoints=None, scans=None, options: FitGeometryOptions | None = None,
        names: dict | None = None, log=None, quiet: bool = True) -> Fitted:
    """Fit ``template`` (modified: personalized in place) to ``keypoints`` (a
    :class:`relight_cli.formats.keypoints.Keypoints`, frames without any measured joint
    skipped) and/or ``scans`` (one [P, 3] point array per keypoint frame).

    Per-frame pose and translation plus shared bone scales (and optional per-vertex
    offsets) are estimated jointly (:func:`relight_cli.hand.fitting.fit`), baked into
    the template's meshes, and with ``options.interpolate`` the frames between the
    keypoint frame numbers filled by slerp.  ``names``: ``template``, ``keypoints`` and
    ``scan`` (the first scan) as messages and errors name them.  ``quiet`` hides the
    frame bar.
    """
    from relight_cli.errors import DataError
    from relight_cli.hand.fitting import FitOptions, fit as fit_hand

    options = options or FitGeometryOptions()
    names = {"template": "template", "keypoints": "keypoints", "scan": "scans", **(names or {})}
    if keypoints is None and scans is None:
        raise ValueError("fit needs keypoints or scans")
    kp, skipped = _measured_frames(keypoints, scans is not None, names["keypoints"])
    if scans is not None and kp is not None and len(scans) != len(kp.positions):
        raise DataError(f"{len(scans)} scans for {len(kp.positions)} keypoint frames; "
                        "give one scan per frame", names["scan"])
    n = len(kp.positions) if kp is not None else len(scans)
    _log_targets(log, template, kp, scans, skipped, n, names, options.interpolate)
    bar = _FrameBar(n, quiet)
    result = fit_hand(template, None if kp is None else kp.positions,
                      None if kp is None else kp.confidence, scans,
                      FitOptions(iterations=options.iterations,
                                 fit_bone_scales=options.bone_scales,
                                 fit_offsets=options.offsets, w_smooth=options.smooth,
                                 seed=options.seed),
                      progress=bar)
    bar.close()
    _personalize(template, result)
    frame_ids = kp.frames if kp is not None else np.arange(n)
    out_frames = _set_motion(template, result, frame_ids, options.interpolate)
    report = _report(template, result, kp, skipped, frame_ids, out_frames)
    hand = _with_other(template) if options.two_hands else template
    return Fitted(hand, report, options.settings())


def fit_hands(template, hands, options: FitGeometryOptions | None = None,
              names: dict | None = None, log=None, quiet: bool = True) -> Fitted:
    """Fit the two hands of one recording into one two-hand hand (``--hand both``).

    ``hands``: two :class:`relight_cli.formats.keypoints.Keypoints` of one recording (frame
    numbers shared), the first of ``template``'s side, the second of the other side.
    hand.npz holds one model and draws the other hand as its mirror image (x → −x), so
    the other hand's keypoints are mirrored onto the template's side and both sequences
    are fitted at once: per-frame pose and translation per hand, one set of bone scales
    shared by both (the hands of one person; the report's ``bone_lengths_mm`` per hand
    shows the bias this leaves on each).  The result has hand 0 (``template``'s side) and
    hand 1 (the other side, ``mirror`` true, its poses the mirror images of the fitted
    ones, identity roots: both hands where the recording has them).  A frame where one
    hand is missing is that hand's missing frame: it is filled by slerp with
    ``options.interpolate`` (each hand clamped to its own first/last measured frame
    outside its range); without it the two-hand output keeps only the frames where both
    are measured, the other hand's fit of that frame still in the report.
    """
    import copy

    from relight_cli.errors import DataError
    from relight_cli.formats.hand_npz import HandInstance
    from relight_cli.hand.fitting import FitOptions, fit as fit_hand
    from relight_cli.hand.poses import interpolate_poses
    from relight_cli.hand.skinning import mirror_pose

    options = options or FitGeometryOptions()
    names = {"template": "template", "keypoints": "keypoints", **(names or {})}
    sides = [kp.side for kp in hands]
    if len(hands) != 2 or sides[0] != template.side or set(sides) != {"left", "right"}:
        raise ValueError(f"fit_hands needs a {template.side} and the other hand, got {sides}")
    kps, skipped = [], []
    for kp in hands:
        if not (kp.confidence > 0).any():
            raise DataError(f"no selected keypoint frame measures any joint of the {kp.side} "
                            "hand: nothing to fit", names["keypoints"])
        kp, missing = _measured_frames(copy.copy(kp), False, names["keypoints"])
        kps.append(kp)
        skipped.append(missing)
    if not options.interpolate and not len(np.intersect1d(kps[0].frames, kps[1].frames)):
        raise DataError(f"the {sides[0]} and the {sides[1]} hand are measured in no common "
                        "frame: a two-hand hand.npz needs both in each frame; --interpolate "
                        "fills each hand's missing frames", names["keypoints"])
    n = [len(kp.frames) for kp in kps]
    _log(log, template_line(template, names["template"]))
    for kp, missing in zip(kps, skipped):
        _log_source(log, kp)
        if missing:
            _log(log, f"skipping {len(missing)} {kp.side}-hand keypoint frame(s) that measure "
                      "no joint: missing frames of that hand")
    _log(log, f"fitting {n[0]} {sides[0]} + {n[1]} {sides[1]} frame(s) to "
              f"{names['keypoints']}: one skeleton, the {sides[1]} hand its mirror image")
    # the other hand's targets mirrored onto the template's side (x → −x)
    positions = np.concatenate([kps[0].positions, kps[1].positions * [-1.0, 1.0, 1.0]])
    confidence = np.concatenate([kps[0].confidence, kps[1].confidence])
    bar = _FrameBar(sum(n), quiet)
    result = fit_hand(template, positions, confidence, None,
                      FitOptions(iterations=options.iterations,
                                 fit_bone_scales=options.bone_scales, w_smooth=options.smooth,
                                 seed=options.seed, sequence_starts=(n[0],)),
                      progress=bar)
    bar.close()
    _personalize(template, result)
    parts = [_rows(result, slice(0, n[0])), _rows(result, slice(n[0], None))]

    frame_ids = [kp.frames for kp in kps]
    if options.interpolate:
        out_frames = np.arange(min(f[0] for f in frame_ids), max(f[-1] for f in frame_ids) + 1)
        motion = [interpolate_poses(f, r.poses, r.translations, out_frames)
                  for f, r in zip(frame_ids, parts)]
    else:
        out_frames = np.intersect1d(*frame_ids)
        motion = []
        for f, r in zip(frame_ids, parts):
            rows = np.searchsorted(f, out_frames)
            motion.append((r.poses[rows], r.translations[rows]))
        dropped = sorted(set(np.union1d(*frame_ids)) - set(out_frames.tolist()))
        if dropped:
            shown = ", ".join(map(str, dropped[:8])) + (", …" if len(dropped) > 8 else "")
            _log(log, f"{len(dropped)} frame(s) measure one hand only (frame {shown}): missing "
                      "from the two-hand output; --interpolate fills them")
    (poses0, trans0), (poses1, trans1) = motion
    template.hands = [
        HandInstance(sides[0], False, np.eye(4), poses0, trans0),
        # the mirrored model with the mirror image of the pose fitted to the mirrored
        # targets puts the joints back on the other hand's own targets
        HandInstance(sides[1], True, np.eye(4), mirror_pose(poses1), trans1 * [-1.0, 1.0, 1.0])]

    per_hand, per_frame = [], []
    for index, (kp, part, missing) in enumerate(zip(kps, parts, skipped)):
        entry = _report(template, part, kp, missing, kp.frames, out_frames)
        del entry["output_frames"], entry["bone_scales"]
        rows = [{"hand": kp.side, **row} for row in entry.pop("per_frame")]
        per_frame += rows
        left_out = [int(f) for f in kp.frames if f not in set(out_frames.tolist())]
        per_hand.append({"hand": kp.side, "index": index, "mirrored": bool(index == 1),
                         **entry, "frames_left_out": left_out})
    all_errors = np.concatenate([p.joint_error_mm for p in parts])
    report = {
        "hands": per_hand,
        "fitted_frames": int(sum(n)),
        "output_frames": [int(f) for f in out_frames],
        "bone_scales": {name: float(s)
                        for name, s in zip(template.joint_names, result.bone_scales)},
        "per_frame": per_frame,
        "mpjpe_mm": _num(np.nanmean(all_errors)),
    }
    return Fitted(template, report, {**options.settings(), "hands": sides})


def _rows(result, rows: slice):
    """The per-frame parts of a FitResult for ``rows`` (shared parts kept)."""
    import dataclasses
    cut = (lambda a: None if a is None else a[rows])
    return dataclasses.replace(result, poses=result.poses[rows],
                               translations=result.translations[rows],
                               joint_error_mm=result.joint_error_mm[rows],
                               joint_median_mm=result.joint_median_mm[rows],
                               energy=cut(result.energy), scan_mm=cut(result.scan_mm),
                               joint_errors_mm=cut(result.joint_errors_mm))


def _log_source(log, kp) -> None:
    """The line saying what the keypoint reader found (a Leap hand, a hand of a
    two-hand relight/keypoints file); nothing for an unnamed hand."""
    src = kp.source
    if src is None:
        return
    if src.get("format") == "leap":
        _log(log, f"Leap recording: {src['hand']} hand (id "
                  f"{', '.join(map(str, src['hand_ids']))}) in "
                  f"{src['recorded_frames'] - src['frames_without_hand']} of "
                  f"{src['recorded_frames']} frames; missing joints (never measured): "
                  f"{', '.join(src['never_observed_joints']) or 'none'}")
    else:
        _log(log, f"{src['format']}: {src['hand']} hand, {src['rows']} row(s)")


def _log(log, message: str) -> None:
    if log is not None:
        log(message)


def _with_other(hand):
    from relight_cli.hand.scene import two_hands
    return two_hands(hand)


def _measured_frames(kp, with_scans: bool, name: str):
    """``kp`` without its frames that measure no joint (missing frames), and their
    frame numbers; every frame must measure one with scans."""
    from relight_cli.errors import DataError
    if kp is None:
        return None, []
    empty = ~(kp.confidence > 0).any(axis=1)
    if empty.all():
        raise DataError("no selected keypoint frame measures any joint (every confidence "
                        "is 0): nothing to fit", name)
    if empty.any() and with_scans:
        raise DataError(f"keypoint frame {int(kp.frames[empty][0])} measures no joint "
                        f"(every confidence is 0); with --scans every frame needs "
                        f"keypoints", name)
    if not empty.any():
        return kp, []
    skipped = [int(f) for f in kp.frames[empty]]
    kp.positions, kp.confidence, kp.frames = \
        kp.positions[~empty], kp.confidence[~empty], kp.frames[~empty]
    return kp, skipped


def _log_targets(log, template, kp, scans, skipped, n, names, interpolate) -> None:
    _log(log, template_line(template, names["template"]))
    if kp is not None:
        _log_source(log, kp)
    if skipped:
        shown = ", ".join(map(str, skipped[:8])) + (", …" if len(skipped) > 8 else "")
        _log(log, f"skipping {len(skipped)} keypoint frame(s) that measure no joint (frame "
                  f"{shown}): " + ("--interpolate fills them" if interpolate else
                                   "missing from the output; --interpolate fills them"))
    _log(log, f"fitting {n} frame(s)" + (f" to {names['keypoints']}" if kp is not None else "")
         + (f" and {len(scans)} scan(s)" if scans else ""))


class _FrameBar:
    """The fitter's progress callback as a frame bar: frames are optimized jointly, so
    the bar advances with the joint stage."""

    def __init__(self, n: int, quiet: bool):
        from relight_cli.progress import progress
        self.n, self.done = n, 0
        self.bar = progress(total=n, desc="fit frames", quiet=quiet)

    def __call__(self, stage, step, total):
        if stage == "fit":
            target = int(self.n * step / total)
            self.bar.update(target - self.done)
            self.done = target

    def close(self):
        self.bar.close()


def _personalize(hand, result) -> None:
    """Bake the fitted bone scales (and offsets) into the template's meshes."""
    from relight_cli.hand.fitting import personalize_mesh
    for which in ("coarse", "fine"):
        m = hand.mesh(which)
        off = result.offsets if (which == "coarse" and result.offsets is not None) else None
        if which == "fine" and result.offsets is not None:
            off = _transfer_offsets(hand.coarse, hand.fine, result.offsets)
        m.vertices = personalize_mesh(m.vertices, m.weights, hand.rest_joints, hand.parents,
                                      result.bone_scales, off)
    hand.rest_joints = result.rest_joints
    hand.bone_scales = result.bone_scales


def _set_motion(hand, result, frame_ids, interpolate: bool):
    """The fitted poses as the hand's frames (slerp-filled between keyframes with
    ``interpolate``); the output's frame numbers."""
    from relight_cli.hand.poses import interpolate_poses
    poses, trans = result.poses, result.translations
    if interpolate and len(frame_ids) > 1:
        out_frames = np.arange(frame_ids[0], frame_ids[-1] + 1)
        poses, trans = interpolate_poses(frame_ids, poses, trans, out_frames)
    else:
        out_frames = frame_ids
    hand.hands = hand.hands[:1]
    hand.hands[0].poses, hand.hands[0].translations = poses, trans
    return out_frames


def _report(hand, result, kp, skipped, frame_ids, out_frames) -> dict:
    from relight_cli.hand.fitting import fit_quality
    per_frame = []
    for i in range(len(frame_ids)):
        row = {"frame": int(frame_ids[i])}
        if kp is not None:
            row["mpjpe_mm"] = _num(result.joint_error_mm[i])
            row["median_joint_error_mm"] = _num(result.joint_median_mm[i])
            row["observed_joints"] = int((kp.confidence[i] > 0).sum())
        if result.scan_mm is not None:
            row["scan_mm"] = _num(result.scan_mm[i])
        per_frame.append(row)
    report = {
        "fitted_frames": len(frame_ids),
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
    return report


def _num(x):
    x = float(x)
    return None if math.isnan(x) else round(x, 4)


def _transfer_offsets(coarse, fine, offsets):
    """Coarse-vertex offsets [Vc, 3] carried to the fine mesh by nearest coarse vertex."""
    from scipy.spatial import cKDTree
    _, idx = cKDTree(coarse.vertices).query(fine.vertices)
    return offsets[idx]
