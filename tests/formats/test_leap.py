"""Leap Motion recordings as fitting targets (formats/leap.md).

Synthetic recordings are written here from known posed hands (the built-in
skeleton with known poses, translations and bone scales), in LeapJS's layout:
millimetres, one pointable per finger with mcp/pip/dip/tip positions, no
wrist and no finger metacarpal bases.  So the mapping, the fit and the report
are checked against the truth.  The real captures in ../shared/data/hands/leap
are used when present.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import run_relight, shared_path
from cli_errors import _one_error

from relight_cli.errors import DataError
from relight_cli.formats.keypoints import read_keypoints
from relight_cli.formats.leap import POINTABLE_JOINTS, leap_keypoints, looks_like_leap
from relight_cli.hand.fitting import FitOptions, bone_lengths, fit, synthetic_truth
from relight_cli.hand.model import JOINT_NAMES, PARENTS, builtin_hand
from relight_cli.hand.skinning import posed_joints

# The joints a LeapJS protocol-6 recording never gives (no wrist, no finger CMC).
NEVER = [0, 5, 10, 15, 20]
OBSERVED = [j for j in range(25) if j not in NEVER]


def _pointables(joints_m, hand_id, extra=False):
    """LeapJS pointables (mm) of one hand from its 25 WebXR joints (metres)."""
    out = []
    for finger, fields in POINTABLE_JOINTS.items():
        p = {"handId": hand_id, "id": 10 * hand_id + finger, "type": finger, "tool": False,
             "extended": True, "direction": [0.0, 1.0, 0.0], "length": 50.0, "width": 18.0}
        for key, j in fields.items():
            if key == "carpPosition" and not extra:
                continue
            p[key] = (np.asarray(joints_m[j]) * 1000).tolist()
        if extra and finger == 0:   # Leap's zero-length thumb metacarpal: carp = mcp
            p["carpPosition"] = p["mcpPosition"]
        out.append(p)
    return out


def leap_recording(tracks, extra=False):
    """A LeapJS recording; ``tracks``: per frame a list of (id, type, joints [25, 3] m)."""
    frames = []
    for n, hands in enumerate(tracks):
        frame = {"id": 1000 + n, "timestamp": 8700 * n, "hands": [], "pointables": [],
                 "gestures": [], "interactionBox": {"center": [0, 200, 0],
                                                    "size": [235.2, 235.2, 147.8]}}
        for hand_id, side, joints in hands:
            palm = np.asarray(joints)[[6, 11, 16, 21]].mean(0) * 1000
            h = {"id": hand_id, "type": side, "confidence": 1.0, "palmPosition": palm.tolist(),
                 "palmNormal": [0.0, -1.0, 0.0], "direction": [0.0, 0.0, -1.0]}
            if extra:
                h["wrist"] = (np.asarray(joints[0]) * 1000).tolist()
            frame["hands"].append(h)
            frame["pointables"] += _pointables(joints, hand_id, extra)
        frames.append(frame)
    return {"metadata": {"formatVersion": 0.1, "generatedBy": "LeapJS Playback 0.1-pre",
                         "frames": len(frames), "protocolVersion": 6}, "frames": frames}


@pytest.fixture(scope="module")
def template():
    return builtin_hand(pose=None)


@pytest.fixture(scope="module")
def truth(template):
    """6 known frames (fist, claw, at-limit poses, random), bone scales ±5%, right hand."""
    return synthetic_truth(template, 6, seed=3)


def _write(tmp_path, obj, name="capture.json"):
    path = tmp_path / name
    path.write_text(json.dumps(obj))
    return path


def _with_nan(text):
    """The JSON text with its first pipPosition x replaced by a NaN literal."""
    return re.sub(r'("pipPosition": \[)[^,]+', r"\1NaN", text, count=1)


# ----------------------------------------------------------------------------- the mapping

def test_mapping_units_axes_and_missing_joints(truth):
    joints = truth[4]
    rec = leap_recording([[(7, "right", joints[n])] for n in range(3)])
    assert looks_like_leap(rec) and not looks_like_leap({"frames": [0, 1]})
    kp = leap_keypoints(rec, "x.json")
    assert kp.side == "right" and kp.frames.tolist() == [0, 1, 2]
    # mm → m, Leap's axes kept: every measured joint lands on its WebXR joint exactly.
    np.testing.assert_allclose(kp.positions[:, OBSERVED], joints[:3, OBSERVED], atol=1e-12)
    # The thumb's mcpPosition is its carpometacarpal joint (WebXR thumb-metacarpal).
    thumb = rec["frames"][0]["pointables"][0]
    np.testing.assert_allclose(np.array(thumb["mcpPosition"]) / 1000,
                               kp.positions[0, JOINT_NAMES.index("thumb-metacarpal")])
    # What Leap does not give is missing (NaN, confidence 0), never invented.
    assert np.isnan(kp.positions[:, NEVER]).all() and (kp.confidence[:, NEVER] == 0).all()
    assert (kp.confidence[:, OBSERVED] == 1).all()
    assert kp.source["never_observed_joints"] == [JOINT_NAMES[j] for j in NEVER]


def test_exported_keypoints_keep_missing_joints_missing(truth, tmp_path):
    """Leap keypoints written as relight/keypoints: missing joints stay missing
    (confidence 0), measured ones round-trip."""
    from relight_cli.formats.keypoints import write_keypoints
    kp = leap_keypoints(leap_recording([[(1, "right", truth[4][0])]]), "x.json")
    path = str(tmp_path / "kp.json")
    write_keypoints(path, kp)
    back = read_keypoints(path)
    assert back.source is None and (back.confidence[:, NEVER] == 0).all()
    np.testing.assert_allclose(back.positions[:, OBSERVED], kp.positions[:, OBSERVED])


def test_wrist_and_carp_positions_are_used_when_present(truth):
    joints = truth[4]
    kp = leap_keypoints(leap_recording([[(1, "right", joints[0])]], extra=True), "x.json")
    assert (kp.confidence == 1).all()
    np.testing.assert_allclose(kp.positions[0], joints[0], atol=1e-12)


def test_hand_selection_and_frames_without_the_hand(truth):
    right = truth[4]
    left = right * [-1, 1, 1]                       # a mirrored hand is a left hand
    tracks = [[(5, "left", left[0])],
              [(5, "left", left[1]), (9, "right", right[1])],
              [(9, "right", right[2])],
              [(9, "right", right[3]), (5, "left", left[3])],
              [(9, "right", right[4])]]
    rec = leap_recording(tracks)
    auto = leap_keypoints(rec, "x.json")            # right is in 4 frames, left in 3
    assert auto.side == "right" and auto.frames.tolist() == [1, 2, 3, 4]
    np.testing.assert_allclose(auto.positions[:, 6], right[1:5, 6], atol=1e-12)
    assert auto.source["frames_without_hand"] == 1 and auto.source["hand_ids"] == [9]
    by_type = leap_keypoints(rec, "x.json", "left")
    assert by_type.side == "left" and by_type.frames.tolist() == [0, 1, 3]
    np.testing.assert_allclose(by_type.positions[:, 1], left[[0, 1, 3], 1], atol=1e-12)
    by_id = leap_keypoints(rec, "x.json", 5)
    np.testing.assert_array_equal(by_id.positions, by_type.positions)
    with pytest.raises(DataError, match="no hand with id 4"):
        leap_keypoints(rec, "x.json", 4)
    only_left = leap_recording([[(5, "left", left[0])]])
    with pytest.raises(DataError, match="no right hand"):
        leap_keypoints(only_left, "x.json", "right")


def test_tools_and_missing_fingers(truth):
    joints = truth[4]
    rec = leap_recording([[(3, "right", joints[0])], [(3, "right", joints[1])]])
    frame = rec["frames"][1]
    frame["pointables"] = [p for p in frame["pointables"] if p["type"] != 2]   # no middle
    frame["pointables"].append({"handId": 3, "id": 99, "tool": True, "type": 1,
                                "tipPosition": [0, 0, 0]})                    # a pen
    kp = leap_keypoints(rec, "x.json")
    middle = [11, 12, 13, 14]
    assert (kp.confidence[1, middle] == 0).all() and np.isnan(kp.positions[1, middle]).all()
    np.testing.assert_allclose(kp.positions[1, 6], joints[1, 6], atol=1e-12)


def test_bad_recordings(tmp_path, truth):
    joints = truth[4]
    good = leap_recording([[(3, "right", joints[0])]])

    def fails(obj, needle, hand=None):
        path = tmp_path / "bad.json"
        path.write_text(obj if isinstance(obj, str) else json.dumps(obj))
        with pytest.raises(DataError, match=needle):
            read_keypoints(str(path), 25, "auto", hand)

    no_hands = json.loads(json.dumps(good))
    for f in no_hands["frames"]:
        f["hands"], f["pointables"] = [], []
    fails(no_hands, "no hands in any")
    fails(_with_nan(json.dumps(good)), "NaN")
    garbage = json.loads(json.dumps(good))
    garbage["frames"][0]["pointables"][1]["pipPosition"] = ["a", 1, 2]
    fails(garbage, "pipPosition' must be 3 numbers")
    short = json.loads(json.dumps(good))
    short["frames"][0]["pointables"][3]["tipPosition"] = [1, 2]
    fails(short, "tipPosition' must be 3 numbers")
    twice = json.loads(json.dumps(good))
    twice["frames"][0]["pointables"].append(dict(twice["frames"][0]["pointables"][1]))
    fails(twice, "two index pointables")
    finger = json.loads(json.dumps(good))
    finger["frames"][0]["pointables"][0]["type"] = 7
    fails(finger, "finger 0")
    side = json.loads(json.dumps(good))
    side["frames"][0]["hands"][0]["type"] = "middle"
    fails(side, "'type' left or right")
    fails({"metadata": {"generatedBy": "LeapJS Playback"}, "frames": []}, "no frames")
    fails({"metadata": {"generatedBy": "LeapJS"}, "frames": [[1, 2, 3]]}, "packed")
    path = tmp_path / "kp.json"
    path.write_text(json.dumps({"keypoints": joints[:1].tolist()}))
    with pytest.raises(DataError, match="not a Leap Motion recording"):
        read_keypoints(str(path), 25, "leap")
    assert read_keypoints(str(path), 25, "auto").source is None


# ----------------------------------------------------------------------------- the fit

def test_fit_recovers_the_known_pose(template, truth, tmp_path):
    """Leap's 20 joints alone pin the pose: the fitted skeleton matches the truth at
    the measured joints and, through the template prior, at the 5 missing ones."""
    poses, trans, scales, rest, joints = truth
    kp = leap_keypoints(leap_recording([[(1, "right", j)] for j in joints]), "x.json")
    result = fit(template, kp.positions, kp.confidence, options=FitOptions(iterations=200))
    fitted = posed_joints(result.poses, result.translations, result.rest_joints, PARENTS)
    err = np.linalg.norm(fitted - joints, axis=-1) * 1000                     # [N, 25] mm
    # Noise-free targets (fist, claw, joints at their limits among them): the
    # measured joints are hit to well under a millimetre (measured: mean 0.07 mm,
    # max 0.35 mm; the bound leaves room for optimizer differences across platforms).
    assert err[:, OBSERVED].mean() < 0.5 and err[:, OBSERVED].max() < 2.0, err[:, OBSERVED]
    # Missing joints are placed by the template's palm while the true bones vary
    # by ±5%: a few mm, not centimetres (measured: mean 2.5 mm, max 6.1 mm).
    assert err[:, NEVER].mean() < 5.0 and err[:, NEVER].max() < 12.0, err[:, NEVER]
    # The report's residuals skip missing joints.
    assert np.isnan(result.joint_errors_mm[:, NEVER]).all()
    assert np.isfinite(result.joint_errors_mm[:, OBSERVED]).all()

    # Missing joints do not matter beyond tolerance: with all 25 given, the
    # measured joints come out the same to within a millimetre ...
    full = fit(template, joints, None, options=FitOptions(iterations=200))
    full_joints = posed_joints(full.poses, full.translations, full.rest_joints, PARENTS)
    diff = np.linalg.norm(full_joints - fitted, axis=-1)[:, OBSERVED] * 1000
    assert diff.mean() < 0.5 and diff.max() < 2.0, diff       # measured: 0.07, 0.3 mm
    # ... and whatever stands in a missing joint's coordinates is ignored.
    garbage = kp.positions.copy()
    garbage[:, NEVER] = 1e3
    again = fit(template, garbage, kp.confidence, options=FitOptions(iterations=200))
    np.testing.assert_array_equal(again.poses, result.poses)


def test_bone_length_statistics_against_direct_computation():
    """The keypoint bone lengths of the report equal |J_child − J_parent| computed
    directly from the JSON's millimetre coordinates."""
    rng = np.random.default_rng(0)
    joints = rng.normal(0, 0.05, (7, 25, 3))
    observed = np.ones((7, 25), bool)
    observed[2, 7] = False
    lengths = bone_lengths(joints, observed, PARENTS)
    direct = np.linalg.norm(joints[:, 8] - joints[:, 7], axis=-1) * 1000
    np.testing.assert_allclose(lengths[[0, 1, 3, 4, 5, 6], 8], direct[[0, 1, 3, 4, 5, 6]])
    assert np.isnan(lengths[2, [7, 8]]).all() and np.isnan(lengths[:, 0]).all()


def _noisy_recording(truth, sigma_mm=1.0, seed=1):
    joints = truth[4] + np.random.default_rng(seed).normal(0, sigma_mm / 1000, truth[4].shape)
    return leap_recording([[(1, "right", j)] for j in joints]), joints


def test_cli_fit_report(run_cli, tmp_path, truth):
    rec, joints = _noisy_recording(truth)
    path = _write(tmp_path, rec)
    out, report = tmp_path / "fit.npz", tmp_path / "fit.json"
    r = run_cli("fit-geometry", "--keypoints", path, "--iterations", "150", "-o", out,
                "--report", report)
    assert r.exit_code == 0, r.output
    assert "Leap recording: right hand (id 1) in 6 of 6 frames" in r.output
    rep = json.loads(report.read_text())
    assert rep["format"] == "relight/fit-report" and rep["version"] == 1
    assert rep["provenance"]["inputs"]["keypoints"]["path"] == str(path)
    assert rep["keypoints"]["format"] == "leap" and rep["keypoints"]["hand"] == "right"
    assert rep["keypoints"]["never_observed_joints"] == [JOINT_NAMES[j] for j in NEVER]
    res = rep["joint_residuals_mm"]
    assert res["all"]["observations"] == 6 * 20
    assert res["per_joint"]["wrist"] is None and res["per_joint"]["index-finger-tip"]["frames"] == 6
    # 1 mm noise per axis: residuals of a few mm at most.
    assert res["all"]["median"] < 2.5 and res["all"]["p95"] < 6.0
    # Bone stability: the recording's lengths match a direct computation; the
    # fitted skeleton is one rigid skeleton (std 0).
    bone = rep["bone_lengths_mm"]["index-finger-phalanx-distal"]
    direct = np.linalg.norm(joints[:, 8] - joints[:, 7], axis=-1) * 1000
    assert bone["from"] == "index-finger-phalanx-intermediate"
    assert bone["keypoints"]["mean"] == pytest.approx(direct.mean(), abs=1e-3)
    assert bone["keypoints"]["std"] == pytest.approx(direct.std(), abs=1e-3)
    assert bone["keypoints"]["max_deviation"] == pytest.approx(
        np.abs(direct - direct.mean()).max(), abs=1e-3)
    assert bone["fitted"]["std"] == 0.0 and bone["fitted"]["frames"] == 6
    assert rep["bone_lengths_mm"]["index-finger-phalanx-proximal"]["keypoints"] is None


def test_cli_hand_choice_missing_frames_interpolate_frame_range(run_cli, tmp_path, truth):
    joints = truth[4][:4]
    left = joints * [-1, 1, 1]
    tracks = [[(2, "left", left[0])], [], [(2, "left", left[2])], [(2, "left", left[3])]]
    path = _write(tmp_path, leap_recording(tracks))
    out, report = tmp_path / "l.npz", tmp_path / "l.json"
    r = run_cli("fit-geometry", "--keypoints", path, "--template", "builtin:left",
                "--hand", "left", "--interpolate", "--iterations", "60", "-o", out,
                "--report", report, "-q")
    assert r.exit_code == 0, r.output
    rep = json.loads(report.read_text())
    assert [row["frame"] for row in rep["per_frame"]] == [0, 2, 3]       # frame 1: no hand
    assert rep["output_frames"] == [0, 1, 2, 3]                          # filled by slerp
    assert rep["keypoints"]["frames_without_hand"] == 1
    r = run_cli("fit-geometry", "--keypoints", path, "--template", "builtin:left",
                "--frames", "2:", "--iterations", "60", "-o", out, "--report", report,
                "-q")
    assert r.exit_code == 0, r.output
    assert json.loads(report.read_text())["output_frames"] == [2, 3]
    from relight_cli.formats.hand_npz import read_hand
    assert read_hand(str(out)).side == "left"


def test_cli_bad_input(run_cli, tmp_path, truth):
    out = tmp_path / "o.npz"
    joints = truth[4]
    good = _write(tmp_path, leap_recording([[(3, "right", joints[0])]]))
    left = _write(tmp_path, leap_recording([[(3, "left", joints[0] * [-1, 1, 1])]]), "left.json")
    _one_error(run_cli("fit-geometry", "--keypoints", left, "--template", "builtin:right",
                       "-o", out), 1, "left hand but the template is a right hand")
    _one_error(run_cli("fit-geometry", "--keypoints", good, "--hand", "8", "-o", out), 1,
               "no hand with id 8")
    _one_error(run_cli("fit-geometry", "--keypoints", good, "--hand", "thumb", "-o", out), 2,
               "--hand must be")
    _one_error(run_cli("fit-geometry", "--keypoints", good, "--frames", "5:9", "-o", out),
               1, "no keypoint frames")
    for bad in ("5", "a:b", "0:10:0", "-1:4"):
        _one_error(run_cli("fit-geometry", "--keypoints", good, "--frames", bad, "-o", out),
                   2, "--frames")
    # a count where the selection goes names the count's option; the old spelling is refused
    _one_error(run_cli("fit-geometry", "--keypoints", good, "--frames", "5", "-o", out),
               2, "a number of frames is --n-frames 5")
    from conftest import run_relight
    old = run_relight("fit-geometry", "--keypoints", good, "--frame-range", "0:2", "-o", out)
    assert old.returncode == 2 and old.stderr.startswith(
        "relight fit-geometry: error: --frame-range was renamed --frames"), old.stderr
    empty = leap_recording([[]])
    _one_error(run_cli("fit-geometry", "--keypoints", _write(tmp_path, empty, "e.json"),
                       "-o", out), 1, "no hands")
    nan = tmp_path / "nan.json"
    nan.write_text(_with_nan(good.read_text()))
    _one_error(run_cli("fit-geometry", "--keypoints", nan, "-o", out), 1, "NaN")
    np.save(tmp_path / "kp.npy", joints[:1])
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "kp.npy", "--hand", "left",
                       "-o", out), 2, "Leap recordings only")
    _one_error(run_cli("fit-geometry", "--keypoints", tmp_path / "kp.npy", "--keypoints-format",
                       "leap", "-o", out), 1, "not a Leap Motion recording")
    _one_error(run_cli("fit-geometry", "--pose", "fist", "--hand", "left", "-o", out), 2,
               "need --keypoints")
    assert not out.exists()
    assert json.loads(good.read_text()) == leap_recording([[(3, "right", joints[0])]])


def test_subprocess_report_to_stdout(tmp_path, truth):
    rec, _ = _noisy_recording(truth, seed=4)
    path = _write(tmp_path, rec)
    out = tmp_path / "fit.npz"
    r = run_relight("fit-geometry", "--keypoints", path, "--keypoints-format", "leap",
                    "--frames", "0:6:2", "--iterations", "60", "-o", out, "--report", "-")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["output_frames"] == [0, 2, 4] and rep["keypoints"]["recorded_frames"] == 6
    assert "Leap recording" in r.stderr and out.exists()


# ----------------------------------------------------------------------------- real captures

@pytest.mark.parametrize("name", ["pinch", "grab", "wave"])
def test_real_recordings_parse(name):
    path = shared_path("hands", "leap", f"{name}.json")
    kp = read_keypoints(str(path))
    assert kp.side == "right" and len(kp.frames) == kp.source["recorded_frames"]
    assert (kp.confidence.sum(1) == 20).all()
    assert kp.source["never_observed_joints"] == [JOINT_NAMES[j] for j in NEVER]
    # Hands hover 10-40 cm above the device (metres now, +Y up).
    y = kp.positions[:, OBSERVED, 1]
    assert 0.05 < np.nanmedian(y) < 0.4
    # Leap tracks one fixed-size skeleton: each bone keeps its length (< 0.01 mm).
    lengths = bone_lengths(kp.positions, kp.confidence > 0, PARENTS)
    measured = ~np.isnan(lengths).all(0)              # 15 bones: both ends measured
    assert measured.sum() == 15
    spread = lengths[:, measured].max(0) - lengths[:, measured].min(0)
    assert spread.max() < 0.01, spread
    # The thumb's first Leap bone (mcp → pip) is its metacarpal: 35-50 mm, as long
    # as the template's thumb metacarpal (46 mm), not the 30 mm proximal phalanx.
    assert 35 < np.nanmean(lengths[:, 2]) < 50


def test_real_pinch_fit(run_cli, tmp_path):
    path = shared_path("hands", "leap", "pinch.json")
    out, report = tmp_path / "pinch.npz", tmp_path / "pinch.json"
    r = run_cli("fit-geometry", "--keypoints", path, "--frames", "0:307:40",
                "--iterations", "150", "-o", out, "--report", report, "-q")
    assert r.exit_code == 0, r.output
    rep = json.loads(report.read_text())
    # Measured: median 0.02 mm, p95 0.3 mm (Leap's skeleton is itself a kinematic
    # hand model, which the template follows closely).
    assert rep["joint_residuals_mm"]["all"]["median"] < 1.0
    assert rep["joint_residuals_mm"]["all"]["p95"] < 3.0
    # Thumb and index tips touch in the pinch (frame 160: ~20 mm apart in the data).
    from relight_cli.formats.hand_npz import read_hand
    h = read_hand(str(out))
    k = rep["output_frames"].index(160)
    j = posed_joints(h.poses[k], h.translations[k], h.rest_joints, h.parents)
    assert np.linalg.norm(j[4] - j[9]) < 0.035


def test_type_tie_is_broken_by_order_of_appearance_not_hash_seed():
    """Issue 52 cause 8: as many left as right frames -> the type seen first in the file
    (frame order, then the frame's `hands` order), whatever PYTHONHASHSEED is."""
    import subprocess
    import sys
    code = (
        "from relight_cli.formats.leap import select_hand\n"
        "frames = [{'hands': [{'id': 1, 'type': %r}, {'id': 2, 'type': %r}]}]\n"
        "print(select_hand(frames, None, 'x.json')[1])\n")
    for first, second in (("left", "right"), ("right", "left")):
        outs = set()
        for seed in ("0", "1", "2", "3", "5", "8"):
            env = {**__import__("os").environ, "PYTHONHASHSEED": seed}
            r = subprocess.run([sys.executable, "-c", code % (first, second)], env=env,
                               capture_output=True, text=True, check=True)
            outs.add(r.stdout.strip())
        assert outs == {first}, (first, outs)


def test_a_left_hand_recording_takes_the_left_template_unless_one_is_given(tmp_path):
    """Issue 53: `fit-geometry --keypoints REC --hand left` failed unless `--template
    builtin:left` was added, and its message suggested "(or --hand)", which was given.
    Without --template the left built-in hand is taken (for --hand left, and for an
    automatic choice that finds a left hand); an explicit --template of the other hand is
    still refused, naming the template to use."""
    from click.testing import CliRunner

    from relight_cli.cli import cli
    from relight_cli.formats.hand_npz import read_hand
    left = builtin_hand("left", pose="relaxed")
    joints = posed_joints(left.poses[0], left.translations[0], left.rest_joints, left.parents)
    rec = _write(tmp_path, leap_recording([[(3, "left", joints)] for _ in range(2)]),
                 "rec.json")
    for extra in (["--hand", "left"], []):
        out = tmp_path / f"fit{len(extra)}.npz"
        r = CliRunner().invoke(cli, ["fit-geometry", "--keypoints", str(rec), *extra,
                                     "--iterations", "20", "-o", str(out)])
        assert r.exit_code == 0, r.output
        assert read_hand(str(out)).side == "left"
    r = CliRunner().invoke(cli, ["fit-geometry", "--keypoints", str(rec), "--hand", "left",
                                 "--template", "builtin:right", "-o", str(tmp_path / "x.npz")])
    assert r.exit_code == 1 and "use --template builtin:left" in r.output
    assert "(or --hand)" not in r.output and not (tmp_path / "x.npz").exists()
