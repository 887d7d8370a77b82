"""``relight personalize``: a subject from a synthetic phone scan (URHand supp. 9), the
universal linear model rendering it, and bad input."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("torch")

from cli_errors import _one_error as one_error  # noqa: E402
from conftest import run_relight  # noqa: E402
from models import STUDENT_CAPTURE, copy_entry  # noqa: E402

LINEAR = {"tex_res": 16, "val_samples": 1}


def _one_error(result, code, needle=None):
    one_error(result, code, needle, command="personalize")


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """A 4-photo scan of the built-in right hand (skin 3, a subject of different bone
    lengths) under builtin:sky, 96² pixels, written as the phone_scan job writes it."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.cli.inputs import load_template
    from relight_cli.hand.fitting import synthetic_truth
    from relight_cli.jobs import personalize as P
    from relight_cli.jobs import phone_scan as PS
    from relight_cli.render.capture import StageSettings

    folder = tmp_path_factory.mktemp("scan")
    template = load_template("builtin:right")
    _, _, scales, rest, _ = synthetic_truth(template, 1, 5)
    truth = type("Truth", (), {"bone_scales": scales, "rest_joints": rest,
                               "poses": template.hands[0].poses[:1],
                               "translations": np.zeros((1, 3))})()
    subject = P.fitted_hand(template, truth)
    settings = StageSettings(skin_seed=3, tex_res=64, aa=1, sss=False)
    data = PS.phone_scan(subject, settings, builtin_envmap("builtin:sky"), views=4, res=96,
                         noise_px=0.5)
    PS.write_scan(str(folder / "scan"), data)
    return folder / "scan", data


def _args(folder, *extra):
    images = sorted(str(p) for p in folder.glob("view_*.exr"))
    return ["personalize", *images, "--cameras", folder / "cameras.json", "--keypoints",
            folder / "keypoints.json", *extra]


@pytest.fixture(scope="module")
def subject(scan, tmp_path_factory):
    folder, _ = scan
    out = tmp_path_factory.mktemp("subject")
    r = run_relight(*_args(folder, "--env", "builtin:sky", "--tex-res", "32", "--iterations",
                           "60", "-o", out / "me.npz", "--report", out / "fit.json",
                           "--preview", out / "me.png"))
    assert r.returncode == 0, r.stderr
    return out


def test_help(run_cli):
    r = run_cli("personalize", "--help")
    assert r.exit_code == 0
    for opt in ("--cameras", "--keypoints", "--masks", "--env", "--checkpoint", "--tex-res",
                "--report", "--preview"):
        assert opt in r.output


def test_subprocess_writes_a_fitted_subject(scan, subject):
    """The subject file: the scan's shape (bone lengths nearer the truth than the
    template's), a mean texture of skin where a white surface is 1/π, a report."""
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.hand.model import PARENTS, builtin_hand
    _, data = scan
    hand = read_hand(str(subject / "me.npz"))
    assert hand.mean_texture is not None and hand.mean_texture.shape == (3, 32, 32)

    def lengths(rest):
        return np.array([np.linalg.norm(rest[j] - rest[PARENTS[j]]) for j in range(1, 25)])
    truth = lengths(data.hand.rest_joints)
    fitted = np.abs(lengths(hand.rest_joints) - truth).mean()
    template = np.abs(lengths(builtin_hand().rest_joints) - truth).mean()
    assert fitted < 0.8 * template, (fitted, template)
    t = hand.mean_texture
    # skin: red above green above blue, an albedo well inside (0, 1) once × π
    means = t.reshape(3, -1).mean(1) * np.pi
    assert means[0] > means[1] > means[2] > 0.05 and means[0] < 1.0, means
    report = json.loads((subject / "fit.json").read_text())
    assert report["format"] == "relight/personalize-report"
    assert max(v["reprojection_px"] for v in report["views"]) < 3.0
    assert report["texels"]["seen_fraction"] > 0.6
    assert (subject / "me.png").stat().st_size > 1000


def test_identical_runs_are_byte_identical(scan, tmp_path, run_cli):
    folder, _ = scan
    outs = []
    for name in ("a", "b"):
        out = tmp_path / "me.npz"
        r = run_cli(*_args(folder, "--env", "builtin:sky", "--tex-res", "16", "--iterations",
                           "5", "-o", out, "-q"))
        assert r.exit_code == 0, r.output
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def test_estimated_lighting_takes_its_level_from_the_checkpoint(scan, tmp_path, run_cli,
                                                                 tiny_models):
    """Without --env, supp. 9's shading map; T̄'s mean luminance is the universal model's
    trained subjects' (read from the checkpoint), and the map has the checkpoint's N."""
    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    from relight_cli.neural.unwrap import luminance
    folder, _ = scan
    ckpt = tmp_path / "linear.pt"
    copy_entry(tiny_models.get("linear", STUDENT_CAPTURE, ["--iters", "1", "-q"], config=LINEAR),
               ckpt)
    out = tmp_path / "me.npz"
    r = run_cli(*_args(folder, "--checkpoint", ckpt, "--iterations", "5", "-o", out, "-q"))
    assert r.exit_code == 0, r.output
    model = load_hand_model(read_checkpoint(str(ckpt)))
    want = float(luminance(np.transpose(model.mean_texture[0].numpy(), (1, 2, 0))).mean())
    t = read_hand(str(out)).mean_texture
    assert t.shape == (3, 16, 16)
    got = float(luminance(np.transpose(t, (1, 2, 0))).mean())
    assert 0.5 * want < got < 2.0 * want        # the level over the seen texels, not all


def test_linear_model_renders_the_hand_files_own_texture(tmp_path, run_cli, tiny_models):
    """A hand.npz carrying T̄ is rendered with it: given the checkpoint's own subject's T̄
    the render equals the plain one exactly; given another T̄ it differs."""
    from relight_cli.formats.exr import read_exr
    from relight_cli.formats.hand_npz import read_hand, write_hand
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    ckpt = tmp_path / "linear.pt"
    copy_entry(tiny_models.get("linear", STUDENT_CAPTURE, ["--iters", "1", "-q"], config=LINEAR),
               ckpt)
    capture_hand = next(p for p in tiny_models.get("capture", STUDENT_CAPTURE).glob("*.npz"))
    hand = read_hand(str(capture_hand))
    model = load_hand_model(read_checkpoint(str(ckpt)))
    own = model.mean_texture[0].numpy()
    renders = {}
    for name, texture in (("plain", None), ("own", own), ("other", own[::-1].copy())):
        hand.mean_texture = texture
        path = tmp_path / f"{name}.npz"
        write_hand(str(path), hand)
        out = tmp_path / f"{name}.exr"
        r = run_cli("relight", path, "builtin:studio", "--model", "linear", "--checkpoint", ckpt,
                    "--size", "20x16", "--env-res", "8x4", "-o", out, "-q")
        assert r.exit_code == 0, r.output
        renders[name] = np.stack([read_exr(str(out)).channels[c] for c in "RGB"])
    np.testing.assert_array_equal(renders["own"], renders["plain"])
    assert np.abs(renders["other"] - renders["plain"]).max() > 1e-4


# ----------------------------------------------------------------------------- bad input

def test_no_lighting_and_no_checkpoint_is_a_usage_error(scan, tmp_path, run_cli):
    folder, _ = scan
    r = run_cli(*_args(folder, "-o", tmp_path / "x.npz"))
    _one_error(r, 2, "--env")
    assert not (tmp_path / "x.npz").exists()


def test_camera_count_must_match(scan, tmp_path, run_cli):
    folder, data = scan
    from relight_cli.formats.camera import write_cameras
    cams = tmp_path / "three.json"
    write_cameras(str(cams), data.cameras[:3])
    images = sorted(str(p) for p in folder.glob("view_*.exr"))
    r = run_cli("personalize", *images, "--cameras", cams, "--keypoints",
                folder / "keypoints.json", "--env", "builtin:sky", "-o", tmp_path / "x.npz")
    _one_error(r, 1, "4 image(s) but 3 camera(s)")
    assert not (tmp_path / "x.npz").exists()


def test_image_without_keypoints_or_alpha(scan, tmp_path, run_cli):
    folder, _ = scan
    from relight_cli.formats.exr import read_exr, write_exr
    img = read_exr(str(folder / "view_00.exr"))
    odd = tmp_path / "other.exr"
    write_exr(str(odd), {c: img.channels[c] for c in "RGB"})
    images = [odd] + sorted(str(p) for p in folder.glob("view_*.exr"))[1:]
    r = run_cli("personalize", *images, "--cameras", folder / "cameras.json", "--keypoints",
                folder / "keypoints.json", "--env", "builtin:sky", "-o", tmp_path / "x.npz")
    _one_error(r, 1, "no keypoints for image 'other.exr'")
    # right name, no alpha and no --masks
    named = tmp_path / "view_00.exr"
    shutil.copy(odd, named)
    images[0] = named
    r = run_cli("personalize", *images, "--cameras", folder / "cameras.json", "--keypoints",
                folder / "keypoints.json", "--env", "builtin:sky", "-o", tmp_path / "x.npz")
    _one_error(r, 1, "no alpha channel; give --masks")
    assert not (tmp_path / "x.npz").exists()


def test_masks_of_another_size_and_empty_masks(scan, tmp_path, run_cli):
    from relight_cli.formats.image import write_png
    folder, _ = scan
    masks = tmp_path / "masks"
    masks.mkdir()
    for p in folder.glob("view_*.exr"):
        write_png(str(masks / f"{p.stem}.png"), np.ones((96, 96, 3)))
    write_png(str(masks / "view_02.png"), np.ones((50, 60, 3)))
    args = _args(folder, "--masks", str(masks / "{stem}.png"), "--env", "builtin:sky", "-o",
                 tmp_path / "x.npz")
    _one_error(run_cli(*args), 1, "mask is 60×50 but its image is 96×96")
    write_png(str(masks / "view_02.png"), np.zeros((96, 96, 3)))
    _one_error(run_cli(*args), 1, "empty mask")
    r = run_cli(*_args(folder, "--masks", "no_stem.png", "--env", "builtin:sky", "-o",
                       tmp_path / "x.npz"))
    _one_error(r, 2, "{stem}")
    assert not (tmp_path / "x.npz").exists()


def _edit_keypoints(folder, tmp_path, edit):
    obj = json.loads((folder / "keypoints.json").read_text())
    edit(obj)
    path = tmp_path / "kp.json"
    path.write_text(json.dumps(obj))
    images = sorted(str(p) for p in folder.glob("view_*.exr"))
    return ["personalize", *images, "--cameras", folder / "cameras.json", "--keypoints", path,
            "--env", "builtin:sky", "-o", tmp_path / "x.npz"]


def test_bad_keypoints(scan, tmp_path, run_cli):
    folder, _ = scan

    def outside(obj):
        obj["views"][1]["keypoints"][5][0] = 500.0

    def other_skeleton(obj):
        obj["views"][0]["keypoints"] = obj["views"][0]["keypoints"][:17]

    def nan(obj):
        obj["views"][0]["keypoints"][0][0] = "NaN"

    def single_view_pose(obj):
        obj["views"][3]["pose"] = 1

    cases = [(outside, "lies outside the 96×96 image"),
             (other_skeleton, "17 keypoints; the mediapipe-21 skeleton has 21"),
             (nan, "view 0"),
             (single_view_pose, "pose 1 has 1 view")]
    for edit, needle in cases:
        _one_error(run_cli(*_edit_keypoints(folder, tmp_path, edit)), 1, needle)
        assert not (tmp_path / "x.npz").exists()


def test_subprocess_bad_input_leaves_nothing(scan, tmp_path):
    folder, _ = scan
    r = run_relight(*_args(folder, "--env", str(tmp_path / "missing.exr"), "-o",
                           tmp_path / "x.npz"))
    _one_error(r, 1)
    assert list(tmp_path.iterdir()) == []


def test_capture_scored_with_a_subject_file(tmp_path, run_cli, tiny_models):
    """relight CAPTURE/ --subject: given the checkpoint's own subject's T̄ the scores equal
    the plain ones; a hand file without T̄, or --subject with a teacher, is refused."""
    from relight_cli.formats.hand_npz import read_hand, write_hand
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.evaluate import load_hand_model
    ckpt = tmp_path / "linear.pt"
    copy_entry(tiny_models.get("linear", STUDENT_CAPTURE, ["--iters", "1", "-q"], config=LINEAR),
               ckpt)
    capture = tiny_models.get("capture", STUDENT_CAPTURE)
    hand = read_hand(str(next(capture.glob("*.npz"))))
    hand.mean_texture = load_hand_model(read_checkpoint(str(ckpt))).mean_texture[0].numpy()
    write_hand(str(tmp_path / "me.npz"), hand)
    common = ["relight", capture, "--model", "linear", "--checkpoint", ckpt, "--splits",
              "fully_lit", "--eval-samples", "1", "-q"]
    assert run_cli(*common, "-o", tmp_path / "plain.json").exit_code == 0
    r = run_cli(*common, "--subject", tmp_path / "me.npz", "-o", tmp_path / "own.json")
    assert r.exit_code == 0, r.output
    plain = json.loads((tmp_path / "plain.json").read_text())
    own = json.loads((tmp_path / "own.json").read_text())
    assert own["metrics"]["fully_lit"]["psnr"] == plain["metrics"]["fully_lit"]["psnr"]
    assert own["provenance"]["settings"]["hands"][0]["subject"] == "own"
    hand.mean_texture = None
    write_hand(str(tmp_path / "bare.npz"), hand)
    r = run_cli(*common, "--subject", tmp_path / "bare.npz", "-o", tmp_path / "x.json")
    assert r.exit_code == 1 and "no mean texture" in r.output
    r = run_cli("relight", capture, "--model", "teacher", "--checkpoint", ckpt, "--subject",
                tmp_path / "me.npz", "-o", tmp_path / "x.json")
    assert r.exit_code == 2 and "--model linear" in r.output
    assert not (tmp_path / "x.json").exists()
