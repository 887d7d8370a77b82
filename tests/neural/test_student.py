"""The distilled student and DRAM (relight_cli/neural/student.py, distill.py): env splits and
rotations, pseudo ground truth, training, renders, learning checks, the linear head."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from relight_cli.errors import DataError  # noqa: E402
from relight_cli.neural.checkpoints import student_model  # noqa: E402
from relight_cli.neural.config import DRAM_LAMBDA_S  # noqa: E402
from models import STUDENT_CAPTURE, STUDENT_TEACHER, STUDENT_TEACHER_CONFIG, copy_entry  # noqa: E402

# the capture and its 10-iteration teacher, made once per run (tests/models.py)
CAPTURE_ARGS = STUDENT_CAPTURE
TEACHER = STUDENT_TEACHER_CONFIG
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "dram_code": 16, "val_samples": 2, "env_holdout": 0.34, "env_res": [8, 16]}
ENVS = ["--envs", "builtin:sky", "--envs", "builtin:studio", "--envs", "builtin:uniform"]


@pytest.fixture(scope="module")
def setup(tmp_path_factory, tiny_models):
    """cap/ and teacher.pt (``train-teacher cap --config teacher.json --iters 10``, made once
    per run: tests/models.py) copied into a folder of this module, with the two configs."""
    root = tmp_path_factory.mktemp("student")
    (root / "teacher.json").write_text(json.dumps(TEACHER))
    (root / "student.json").write_text(json.dumps(STUDENT))
    copy_entry(tiny_models.get("capture", CAPTURE_ARGS), root / "cap")
    copy_entry(tiny_models.get(STUDENT_TEACHER[0], CAPTURE_ARGS, *STUDENT_TEACHER[1:]),
               root / "teacher.pt")
    return root


def _invoke(*args):
    from click.testing import CliRunner

    from relight_cli.cli import cli
    return CliRunner().invoke(cli, [str(a) for a in args])


def _distill(setup, out, *extra):
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                setup / "student.json", "-q", "-o", out, *extra)
    assert r.exit_code == 0, r.output
    return out


def _sky(h=16, w=32):
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    return discretize_env(builtin_envmap("builtin:sky"), h, w)


# ---------------------------------------------------------------- env maps


def test_env_split_is_seeded_and_disjoint():
    from relight_cli.neural.distill import split_envs
    names = [f"e{i}" for i in range(20)]
    tr, ev = split_envs(names, 0.2, 3)
    assert (tr, ev) == split_envs(names, 0.2, 3)
    assert len(ev) == 4 and not set(tr) & set(ev) and sorted(tr + ev) == list(range(20))
    assert split_envs(names, 0.2, 4) != (tr, ev)
    assert split_envs(["a"], 0.17, 0) == ([0], [])
    with pytest.raises(DataError, match="no training env maps"):
        split_envs(["a", "b"], 0.9, 0)


def test_rotation_is_exact_about_y():
    from relight_cli.envmap import latlong_pixel, rotation_y
    from relight_cli.neural.distill import rotate_env
    env = _sky()
    k = 5
    rot = rotate_env(env, k)
    # power is kept exactly; a full turn and turning back restore the map (seam averaged)
    np.testing.assert_allclose((rot.radiance * rot.solid_angle[:, None]).sum(0),
                               (env.radiance * env.solid_angle[:, None]).sum(0), rtol=1e-12)
    back = rotate_env(rot, -k)
    np.testing.assert_allclose(back.radiance.reshape(16, 32, 3)[:, 1:-1],
                               env.radiance.reshape(16, 32, 3)[:, 1:-1], rtol=1e-12)
    assert rotate_env(env, 31) is env
    # the rotated map's value towards R·d is the original's towards d (away from the seam)
    theta = 360.0 * k / (env.width - 1)
    inner = np.zeros((16, 32), bool)
    inner[:, 1:-1] = True
    inner = inner.ravel()
    hits = []
    for sign in (1, -1):
        R = rotation_y(sign * theta)
        px = latlong_pixel(env.directions @ R.T, env.height, env.width)
        idx = np.rint(px[:, 1]).astype(int) * env.width + np.rint(px[:, 0]).astype(int)
        ok = inner & inner[idx]
        hits.append(np.allclose(rot.radiance[idx][ok], env.radiance[ok], rtol=1e-12))
    assert any(hits)


def test_wrist_env_identity_and_turn():
    from relight_cli.envmap import rotation_y
    from relight_cli.neural.distill import rotate_env, wrist_env
    env = _sky()
    np.testing.assert_array_equal(wrist_env(env, np.eye(3)), env.radiance.reshape(-1))
    # a wrist turned about +Y by whole longitude steps sees the rolled map
    k = 4
    inner = np.zeros((16, 32, 3), bool)
    inner[:, 3:-3] = True
    inner = inner.ravel()
    turned = [wrist_env(env, rotation_y(s * 360.0 * k / (env.width - 1))) for s in (1, -1)]
    rolled = rotate_env(env, k).radiance.reshape(-1)
    assert any(np.allclose(t[inner], rolled[inner]) for t in turned)


def test_mirror_is_exact_in_longitude():
    """The mirrored map's value at longitude −φ is the original's at φ (cells matched by
    the grid's pixel-centre angles, the seam's −π and +π columns kept apart; the
    directions then mirror x), and its power is kept."""
    from relight_cli.envmap import latlong_angles
    from relight_cli.neural.distill import mirror_env
    for h, w in ((8, 16), (16, 32)):
        env = _sky(h, w)
        env.radiance[:] *= np.random.default_rng(0).uniform(0.5, 2.0, env.radiance.shape)
        mir = mirror_env(env)
        _, lon = latlong_angles(h, w)
        col = np.argmin(np.abs(-lon[:, None] - lon[None]), axis=1)
        np.testing.assert_allclose(lon[col], -lon, atol=1e-12)
        match = (np.arange(h)[:, None] * w + col[None]).ravel()
        flipped = env.directions * np.array([-1.0, 1.0, 1.0])
        np.testing.assert_allclose(env.directions[match], flipped, atol=1e-12)
        np.testing.assert_array_equal(mir.radiance, env.radiance[match])
        np.testing.assert_allclose((mir.radiance * mir.solid_angle[:, None]).sum(0),
                                   (env.radiance * env.solid_angle[:, None]).sum(0),
                                   rtol=1e-12)


def test_mixed_env_maps(monkeypatch):
    """``env_augment: mix``: seeded, finite, non-negative, on the training maps' grid; one
    uniform map with no tint is uniform, and its sun is one cell carrying the drawn share
    of the power, at a cell drawn uniformly on the sphere (∝ solid angle)."""
    from relight_cli.envmap import DiscreteEnv
    from relight_cli.neural import distill as D
    sky = _sky(8, 16)
    studio = D.rotate_env(sky, 3)
    maps = [sky, studio]
    a, b = (D.mix_env(maps, np.random.default_rng(7)) for _ in range(2))
    np.testing.assert_array_equal(a.radiance, b.radiance)
    draws = [D.mix_env(maps, np.random.default_rng(k)) for k in range(20)]
    assert len({d.radiance.tobytes() for d in draws}) == 20
    for d in draws:
        assert np.isfinite(d.radiance).all() and (d.radiance >= 0).all()
        assert d.directions is sky.directions and (d.height, d.width) == (8, 16)
        assert not any(np.allclose(d.radiance / D.env_scale(d), m.radiance / D.env_scale(m))
                       for m in maps)
    uniform = DiscreteEnv(sky.directions, sky.solid_angle, np.full_like(sky.radiance, 2.0),
                          8, 16, "uniform")
    monkeypatch.setattr(D, "MIX_MAPS", 1)
    monkeypatch.setattr(D, "MIX_TINT", 0.0)
    monkeypatch.setattr(D, "MIX_SUN_P", 0.0)
    flat = D.mix_env([uniform], np.random.default_rng(1)).radiance
    np.testing.assert_allclose(flat, flat[0, 0], rtol=1e-12)
    assert 0.2 <= flat[0, 0] <= 1.0                      # U(0.2, 1) over the map's scale 2
    monkeypatch.setattr(D, "MIX_SUN_P", 1.0)
    omega = sky.solid_angle
    heights = []
    for k in range(3000):
        rad = D.mix_env([uniform], np.random.default_rng(k)).radiance
        base = np.median(rad[:, 0])
        sun = np.flatnonzero(np.abs(rad[:, 0] - base) > 1e-12 * base)
        assert len(sun) == 1
        share = (rad[sun[0], 0] - base) * omega[sun[0]] / (base * omega.sum())
        assert D.MIX_SUN_SHARE[0] * (1 - 1e-9) <= share <= D.MIX_SUN_SHARE[1] * (1 + 1e-9)
        heights.append(abs(sky.directions[sun[0], 1]))
    # uniform on the sphere: E|y| over the grid's cells weighted by solid angle (0.5 on the
    # continuous sphere); cells drawn with equal odds would give 0.64 on this 8-row grid
    expected = float((np.abs(sky.directions[:, 1]) * omega).sum() / omega.sum())
    assert abs(np.mean(heights) - expected) < 0.02
    assert abs(expected - np.abs(sky.directions[:, 1]).mean()) > 0.1


# ---------------------------------------------------------------- pseudo ground truth


def test_pseudo_ground_truth_equals_teacher_render(setup, tmp_path):
    """Target = Σ_m b_m C_m equals the teacher's own env render (engine and CLI)."""
    from relight_cli.formats.camera import write_cameras
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.formats.exr import read_exr
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.distill import TeacherTargets
    from relight_cli.neural.teacher import env_light_inputs, render_lights
    from relight_cli.neural.checkpoints import teacher_model as model_from_checkpoint

    net, cfg, mean = model_from_checkpoint(read_checkpoint(str(setup / "teacher.pt")))
    data = CaptureData(str(setup / "cap"), cfg.tex_res, cfg.aa)
    env = _sky()
    targets = TeacherTargets(net, cfg, data, env, cache_dir=str(tmp_path / "cache"), budget_mb=0)
    pose, cam = 1, data.capture.cameras[0]
    target = targets.image(pose, cam.name, env).numpy()
    texels = data.texels(pose)
    gb = data.gbuffer(pose, cam)
    ref = render_lights(net, texels, gb, data.poses(pose), *env_light_inputs(texels, env, True),
                        cfg.visibility, cfg.falloff).numpy()
    scale = float(np.abs(ref).max())
    assert scale > 0
    assert float(np.abs(target - ref).max()) <= 1e-5 * scale
    # spilled to the disk cache (budget 0), read back memory-mapped: same values
    assert list((tmp_path / "cache").glob("*.npy"))
    again = targets.image(pose, cam.name, env).numpy()
    np.testing.assert_array_equal(again, target)
    # the command's render of the same pose, camera and discretization
    write_cameras(str(tmp_path / "cam.json"), [cam])
    r = _invoke("relight", setup / "cap" / "hand.npz", "builtin:sky", "--model", "teacher",
                "--checkpoint", setup / "teacher.pt", "--frame", pose, "--camera",
                tmp_path / "cam.json", "-q", "-o", tmp_path / "t.exr")
    assert r.exit_code == 0, r.output
    im = read_exr(str(tmp_path / "t.exr"))
    cli_img = np.stack([im.channels[c] for c in "RGB"], -1)
    assert float(np.abs(cli_img - target).max()) <= 1e-5 * scale


# ---------------------------------------------------------------- training and renders


def test_distillation_lowers_the_loss(setup):
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.checkpoints import teacher_model as model_from_checkpoint
    from relight_cli.neural.train import fit

    net, tcfg, mean = model_from_checkpoint(read_checkpoint(str(setup / "teacher.pt")))
    data = CaptureData(str(setup / "cap"), tcfg.tex_res, tcfg.aa)
    envs = [_sky()]
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    envs.append(discretize_env(builtin_envmap("builtin:studio"), 16, 32))
    cfg = StudentConfig.from_dict({**STUDENT, "iters": 40, "env_holdout": 0.0,
                                   "lambda_vgg": 0.0, "env_res": [16, 32]})
    targets = D.TeacherTargets(net, tcfg, data, envs[0])
    task = D.StudentTask(data, cfg, targets, envs, [0, 1], [], ["sky", "studio"])

    def loss_of(model):
        with torch.no_grad():
            return float(np.mean([task.loss(model, it, 10 ** 6 + i, "cpu")[1]["mse"]
                                  for i, it in enumerate(task.items)]))

    torch.manual_seed(0)
    before = loss_of(task.build("cpu"))
    result = fit(task, cfg, torch.device("cpu"), show_progress=False)
    trained, _ = student_model(result.checkpoint)
    after = loss_of(trained)
    assert after < 0.5 * before, (before, after)
    assert "vs_teacher" in result.metrics and "vs_ground_truth" in result.metrics
    # the synthetic capture gives the ground-truth split its ceiling at the student's N
    truth = result.metrics["vs_ground_truth"]
    assert truth["gap_to_ceiling"] == pytest.approx(truth["ceiling"]["psnr"] - truth["psnr"])
    assert truth["ceiling"]["psnr"] > truth["psnr"]       # 40 iterations: far from it
    # a student of another N than its teacher gets texels of its own N (made once)
    from types import SimpleNamespace
    other = SimpleNamespace(data=data, config=SimpleNamespace(tex_res=32))
    pose = int(data.splits()["env"][0][1]["pose"])      # a held-out env render's pose
    texels = D._student_texels(other, pose)
    assert texels.tex_res == 32 and D._student_texels(other, pose) is texels
    assert D._student_texels(task, pose) is data.texels(pose, held_out=True)


def test_identical_runs_identical_weights_and_renders(setup, tmp_path):
    out = tmp_path / "s.pt"
    _distill(setup, out, "--iters", "3", "--metrics-out", tmp_path / "v.json")
    first = out.read_bytes()
    _distill(setup, out, "--iters", "3", "--metrics-out", tmp_path / "v.json")
    assert out.read_bytes() == first
    renders = []
    for _ in range(2):
        path = tmp_path / "a.exr"
        r = _invoke("relight", setup / "cap" / "hand.npz", "builtin:studio", "--model", "student",
                    "--checkpoint", out, "--size", "24x24", "-q", "-o", path)
        assert r.exit_code == 0, r.output
        renders.append(path.read_bytes())
    assert renders[0] == renders[1]
    record = json.loads((tmp_path / "v.json").read_text())
    assert record["kind"] == "validation" and "vs_teacher" in record["metrics"]


@pytest.mark.parametrize("student", ["student", "dram"])
def test_mixed_env_training_resumes_exactly(setup, tmp_path, student):
    """``env_augment: mix`` draws each sample's map from the run's seeded RNG stream, so
    2 + 2 resumed iterations are 4 uninterrupted ones, bit for bit; and the run is not
    the plain one (the maps it trained on differ)."""
    from relight_cli.neural.checkpoints import read_checkpoint
    (tmp_path / "mix.json").write_text(json.dumps({**STUDENT, "env_augment": "mix",
                                                   "student": student}))
    (tmp_path / "plain.json").write_text(json.dumps({**STUDENT, "student": student}))

    def run(out, config, *extra):
        r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                    config, "-q", "-o", out, *extra)
        assert r.exit_code == 0, r.output
        return read_checkpoint(str(out))
    whole = run(tmp_path / "whole.pt", tmp_path / "mix.json", "--iters", "4")
    run(tmp_path / "half.pt", tmp_path / "mix.json", "--iters", "2")
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--resume",
                tmp_path / "half.pt", "--iters", "4", "-q", "-o", tmp_path / "resumed.pt")
    assert r.exit_code == 0, r.output
    resumed = read_checkpoint(str(tmp_path / "resumed.pt"))
    plain = run(tmp_path / "plain.pt", tmp_path / "plain.json", "--iters", "4")
    for k, v in whole["weights"].items():
        assert torch.equal(v, resumed["weights"][k]), k
    assert any(not torch.equal(v, plain["weights"][k]) for k, v in whole["weights"].items())


@pytest.mark.parametrize("student", ["student", "dram", "linear"])
def test_student_renders_one_and_two_hands(setup, tmp_path, student):
    from conftest import run_relight
    from relight_cli.formats.exr import read_exr
    if student == "linear":                    # the linear head (the cpu preset's)
        (tmp_path / "lin.json").write_text(json.dumps({**STUDENT, "head": "linear"}))
        r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                    tmp_path / "lin.json", "--iters", "2", "-q", "-o", tmp_path / "lin.pt")
        assert r.exit_code == 0, r.output
        ckpt = tmp_path / "lin.pt"
    else:
        ckpt = _distill(setup, tmp_path / f"{student}.pt", "--iters", "2", "--student", student)
    for hand in (setup / "cap" / "hand.npz", "builtin:two:fist"):
        out = tmp_path / "img.exr"
        r = run_relight("relight", hand, "builtin:sky", "--model", "student", "--checkpoint", ckpt,
                        "--size", "32x24", "-o", out, "--preview", tmp_path / "img.png", "-q")
        assert r.returncode == 0, r.stderr
        im = read_exr(str(out))
        rgb = np.stack([im.channels[c] for c in "RGB"], -1)
        # a 2-iteration smoke test: whether learning works is checked by the learning gates
        assert (im.width, im.height) == (32, 24) and np.isfinite(rgb).all()
        assert im.attributes["relight.model"] == "student"


def test_dram_traces_no_texel_features(setup, tmp_path, monkeypatch):
    """DRAM reads no texel features: distill and relight never trace a pose's visibility for
    it (bake's PoseFeatures made to raise), and its texture is what the network gives with
    any features of the right size (it reads only their size)."""
    import relight_cli.bake as bake
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural import distill as DI

    def traced(*args, **kwargs):
        raise AssertionError("DRAM traced texel features")
    monkeypatch.setattr(bake, "PoseFeatures", traced)
    ckpt = _distill(setup, tmp_path / "dram.pt", "--iters", "2", "--student", "dram")
    net, config = student_model(read_checkpoint(str(ckpt), kind="student"))
    r = _invoke("relight", setup / "cap" / "hand.npz", "builtin:sky", "--model", "student",
                "--checkpoint", ckpt, "--env-res", "16x8", "--size", "16x12", "-q",
                "-o", tmp_path / "img.exr")
    assert r.exit_code == 0, r.output
    denv = _sky(8, 16)
    poses = np.zeros((1, (net.film[0].in_features - config.dram_code) // 3 + 1, 3))
    wrists = [np.eye(3)]
    n = config.tex_res
    with torch.no_grad():
        none = DI.student_forward(net, config, None, poses, denv, wrists, "cpu")[0]
        feats = np.random.default_rng(0).random((1, 12, n, n)).astype(np.float32)
        given = DI.student_forward(net, config, feats, poses, denv, wrists, "cpu")[0]
    assert torch.equal(none, given) and none.shape == (3, n, n)
    # the same network reads the light: another env map gives another texture
    with torch.no_grad():
        other = DI.student_forward(net, config, None, poses, DI.rotate_env(denv, 4), wrists,
                                   "cpu")[0]
    assert not torch.equal(none, other)


def test_student_is_scale_equivariant(setup, tmp_path):
    """Normalizing by the env's mean radiance: a 10× brighter env gives a 10× brighter image."""
    from relight_cli.envmap import DiscreteEnv
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural import distill as D
    from relight_cli.neural.teacher import composite
    from relight_cli.render.gbuffer import render_gbuffer
    from relight_cli.hand.model import builtin_hand
    from relight_cli.hand.scene import posed_meshes, preview_camera

    ckpt = _distill(setup, tmp_path / "s.pt", "--iters", "2")
    net, cfg = student_model(read_checkpoint(str(ckpt), kind="student"))
    hand = builtin_hand("right", "fist")
    feats = D.StudentFeatures(cfg)
    pose = feats.pose(hand, 0)
    meshes = posed_meshes(hand, 0, "fine")
    cam = preview_camera(meshes, 24, 24)
    gb = render_gbuffer(meshes, cam, 1)
    env = _sky(8, 16)
    bright = DiscreteEnv(env.directions, env.solid_angle, env.radiance * 10, 8, 16)
    images = []
    with torch.no_grad():
        for e in (env, bright):
            maps = feats.maps(pose, e, cam.center)
            tex = D.student_forward(net, cfg, maps, D.hand_poses(hand, 0), e,
                                    D.wrist_rotations(hand, 0), "cpu")
            images.append(composite(tex, gb).numpy())
    np.testing.assert_allclose(images[1], 10 * images[0], rtol=1e-4, atol=1e-7)


def test_student_renders_on_its_render_grid(setup, tmp_path):
    """``render_env_res``: trained on the same grid, so bit-identical weights; scored and
    rendered on its own grid (the held-out ground truth records it and differs); ``relight
    --env-res`` takes any grid for the texel-aligned student, DRAM's must be its own."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.formats.exr import read_exr
    runs = {}
    for name, extra in (("train", {}), ("fine", {"render_env_res": [16, 32]})):
        (tmp_path / f"{name}.json").write_text(json.dumps({**STUDENT, "head": "linear",
                                                           **extra}))
        r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                    tmp_path / f"{name}.json", "--iters", "3", "-q", "-o", tmp_path / f"{name}.pt",
                    "--metrics-out", tmp_path / f"{name}.metrics.json")
        assert r.exit_code == 0, r.output
        runs[name] = (read_checkpoint(str(tmp_path / f"{name}.pt")),
                      json.loads((tmp_path / f"{name}.metrics.json").read_text())["metrics"])
    (train, m_train), (fine, m_fine) = runs["train"], runs["fine"]
    for k, v in train["weights"].items():
        assert torch.equal(v, fine["weights"][k]), k
    assert m_train["vs_teacher"] == m_fine["vs_teacher"]          # the training grid's
    assert m_train["vs_ground_truth"]["env_res"] == [8, 16]
    assert m_fine["vs_ground_truth"]["env_res"] == [16, 32]
    assert m_fine["vs_ground_truth"]["psnr"] != m_train["vs_ground_truth"]["psnr"]
    assert m_fine["vs_ground_truth"]["ceiling"] == m_train["vs_ground_truth"]["ceiling"]

    def render(ckpt, *extra):             # in process: the subprocess path is tested above
        out = tmp_path / "img.exr"
        r = _invoke("relight", setup / "cap" / "hand.npz", "builtin:sky", "--model",
                    "student", "--checkpoint", ckpt, "--size", "24x20", "-o", out, "-q",
                    *extra)
        if r.exit_code:
            return r
        im = read_exr(str(out))
        settings = json.loads(im.attributes["relight.provenance"])["settings"]
        return settings["env_res"], np.stack(
            [im.channels[c] for c in "RGB"], -1)
    grid, own = render(tmp_path / "fine.pt")
    assert grid == [16, 32]
    grid, coarse = render(tmp_path / "fine.pt", "--env-res", "16x8")
    assert grid == [8, 16] and np.isfinite(coarse).all() and not np.array_equal(own, coarse)
    assert render(tmp_path / "train.pt")[0] == [8, 16]
    assert render(tmp_path / "train.pt", "--env-res", "64x32")[0] == [32, 64]
    dram = _distill(setup, tmp_path / "dram.pt", "--iters", "1", "--student", "dram")
    r = render(dram, "--env-res", "32x16")
    assert r.exit_code == 2 and "DRAM" in r.output and len(r.output.strip().splitlines()) == 1
    assert render(dram)[0] == [8, 16]
    # the Python job refuses it too (before any frame)
    from relight_cli.envmap import discretize_env
    from relight_cli.cli.inputs import load_hand
    from relight_cli.jobs import relight_hand as J
    net, config = student_model(read_checkpoint(str(dram), kind="student"))
    denv = discretize_env(builtin_envmap("builtin:sky"), 16, 32)
    with pytest.raises(ValueError, match="DRAM renders on its training grid"):
        next(J.student(load_hand(str(setup / "cap" / "hand.npz")), [0], None, net, config,
                       denv, 1))


def test_student_features_converge_with_the_grid(setup):
    """Why a student renders on a finer grid than it trained on: its features are
    integrals over the sphere, and a finer grid's are closer to the finest (under the
    studio's softboxes; a sun smaller than a cell converges only on average over its
    positions within the cell)."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    from relight_cli.neural.data import CaptureData
    cfg = StudentConfig.from_dict(STUDENT)
    data = CaptureData(str(setup / "cap"), 16, 1)
    eye = data.capture.cameras[0].center
    maps = {}
    for grid in ((4, 8), (8, 16), (16, 32), (64, 128)):
        feats = D.StudentFeatures(cfg, env_res=grid)
        maps[grid] = feats.maps(feats.pose(data.hand, 0),
                                discretize_env(builtin_envmap("builtin:studio"), *grid), eye)
    ref = maps[(64, 128)]
    err = [float(np.abs(maps[g] - ref).mean() / np.abs(ref).mean())
           for g in ((4, 8), (8, 16), (16, 32))]
    assert err[0] > err[1] > err[2], err
    assert err[2] < 0.5 * err[1], err


def test_student_refuses_point_lights(setup, tmp_path):
    ckpt = _distill(setup, tmp_path / "s.pt", "--iters", "1")
    lights = tmp_path / "l.json"
    lights.write_text(json.dumps({"format": "relight/lights", "version": 1,
                                  "lights": [{"position": [0, 1, 1]}]}))
    r = _invoke("relight", setup / "cap" / "hand.npz", "--lights", lights, "--model", "student",
                "--checkpoint", ckpt, "-q", "-o", tmp_path / "x.exr")
    assert r.exit_code == 2 and "env-map model" in r.output
    assert not (tmp_path / "x.exr").exists()


def test_distill_on_real_hdris(setup, tmp_path, shared):
    """The Poly Haven HDRIs as a folder of --envs: split, rotated, distilled, validated."""
    folder = shared("envmaps", "polyhaven")
    out = tmp_path / "real.pt"
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", "--envs", folder, "--config",
                setup / "student.json", "--iters", "3", "-q", "-o", out, "--metrics-out",
                tmp_path / "v.json")
    assert r.exit_code == 0, r.output
    ck = torch.load(out, weights_only=True)
    envs = json.loads(ck["extra"]["envs"])
    assert len(envs["train"]) + len(envs["eval"]) == 6 and envs["eval"]
    assert not set(envs["train"]) & set(envs["eval"])
    metrics = json.loads((tmp_path / "v.json").read_text())["metrics"]
    assert np.isfinite(metrics["vs_teacher"]["mse"])


def test_fixed_evaluation_envs(setup, tmp_path):
    """--eval-envs: those maps only evaluate, every --envs map trains."""
    out = tmp_path / "fixed.pt"
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", "--envs", "builtin:sky",
                "--envs", "builtin:uniform", "--eval-envs", "builtin:studio", "--config",
                setup / "student.json", "--iters", "2", "--env-res", "8x4", "-q", "-o", out)
    assert r.exit_code == 0, r.output
    ckpt = torch.load(out, weights_only=True)
    envs = json.loads(ckpt["extra"]["envs"])
    assert envs == {"train": ["sky", "uniform"], "eval": ["studio"]}
    assert json.loads(ckpt["config"])["env_res"] == [4, 8]        # --env-res is WxH, stored (H, W)


# ---------------------------------------------------------------- learning is alive
#
# The teacher in the module fixture is 10 iterations old and its renders are nearly
# constant: on held-out poses the best constant per image scores an MSE of 4e-4 against
# them, T̄ · diffuse / π (capture T̄, LSQ scale) 0.18, and a student fed zeroed features
# 0.041 — a "beats the baseline" gate against it passes for a dead light path (measured).
# These checks use instead a pseudo ground truth the student's own inputs can explain —
# a uniform albedo ρ on bake-features' visibility-aware diffuse map plus a Phong α = 16
# lobe (a linear map of two of its input channels) — and a strong non-learned baseline
# that knows all of it but the lobe: T̄ · diffuse / π with T̄ = ρ (this teacher's mean
# texture) and one least-squares scale per colour channel fitted on the training items.
# Both are scored against the same targets, on the held-out poses under every env map
# (the evaluation map never trained on).  Env rotations are off: with them the held-out
# score of these short runs swings by 10× between evaluations (measured), too noisy for
# a gate.  Features are memoized (deterministic) so a run is not all baking.

ALBEDO = (0.6, 0.4, 0.3)
LOBE = 0.5
#: DRAM's interior texture std over the teacher's, and their correlation, at least (measured
#: over seeds 0–3 on this capture: 0.77–1.12 and 0.26–0.36 with Eq. 11's head scale; with
#: the presets' texture-unit head, DRAM_LAMBDA_S: 1.17–1.35 and 0.30–0.41; the spatially
#: constant sabotage: 0 and 0; the previous DRAM design: 0.17 and 0.19; untrained: ~1e-5).
DRAM_STD, DRAM_CORR = 0.3, 0.15
LEARN = {**STUDENT, "iters": 300, "batch": 4, "lambda_vgg": 0.0, "rotations": False,
         "env_holdout": 0.0}


class _FeatureTeacher:
    """Pseudo ground truth ρ/π · diffuse + k_s · phong16 from bake-features' maps (cached)."""

    def __init__(self, data, config):
        from relight_cli.neural.distill import StudentFeatures
        self.data = data
        self.features = StudentFeatures(config)
        self.albedo = torch.tensor(ALBEDO)[:, None, None]
        self._cache = {}

    def diffuse(self, pose, camera, denv) -> torch.Tensor:
        """[H, 3, N, N] the student's diffuse input (irradiance)."""
        return self._maps(pose, camera, denv)[:, :3]

    def _maps(self, pose, camera, denv):
        key = (pose, camera, denv.name)
        if key not in self._cache:
            pf = self.features.pose(self.data.hand, pose, key=(False, pose))
            self._cache[key] = torch.from_numpy(self.features.maps(
                pf, denv, self.data._cameras[camera].center))
        return self._cache[key]

    def texture(self, pose, camera, denv, held_out=False) -> list:
        maps = self._maps(pose, camera, denv)
        return list(self.albedo / np.pi * maps[:, :3] + LOBE * maps[:, 3:6])

    def image(self, pose, camera, denv, held_out=False) -> torch.Tensor:
        from relight_cli.neural.teacher import composite
        return composite(self.texture(pose, camera, denv),
                         self.data.gbuffer(pose, self.data._cameras[camera]))


def _cached_maps(features):
    """Memoize a StudentFeatures' maps (deterministic) so a short run is not all baking."""
    maps, cache = features.maps, {}

    def cached(pose_features, denv, eye):
        key = (id(pose_features), denv.name, tuple(np.asarray(eye, float)))
        if key not in cache:
            cache[key] = maps(pose_features, denv, eye)
        return cache[key]
    features.maps = cached


class _ConstantDRAM(torch.nn.Module):
    """Sabotage: DRAM whose texture is its own spatial mean (cannot vary in space)."""

    kind = "dram"

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, *args, return_raw=False, **kwargs):
        tex, raw = self.net(*args, return_raw=True, **kwargs)
        tex, raw = (t.mean((2, 3), keepdim=True).expand_as(t) for t in (tex, raw))
        return (tex, raw) if return_raw else tex


class _NoLightDRAM(_ConstantDRAM):
    """Sabotage: DRAM given one env code (zeros) whatever the env map (light path cut)."""

    def forward(self, features, pose, env_code=None, return_raw=False):
        return self.net(features, pose, torch.zeros_like(env_code), return_raw=return_raw)


@pytest.fixture(scope="module")
def learning(setup):
    """run(student, sabotage, **config) → trained model; score(model) → held-out MSEs."""
    from relight_cli.builtin_envs import builtin_envmap
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.losses import masked_mse
    from relight_cli.neural.teacher import composite
    from relight_cli.neural.train import fit

    data = CaptureData(str(setup / "cap"), 16, 1)
    h, w = STUDENT["env_res"]
    names = ["sky", "studio", "uniform"]
    envs = [discretize_env(builtin_envmap("builtin:" + n), h, w) for n in names]
    train_env, eval_env = [0, 1], [2]
    teacher = _FeatureTeacher(data, StudentConfig.from_dict(LEARN))
    cams = [c.name for c in data.capture.cameras]
    train = [(p, c, e) for p in sorted({f.pose for f in data.train_frames
                                        + data.train_fully_lit_frames})
             for c in cams for e in train_env]
    held = [(f.pose, c, e) for f in data.heldout_frames for c in cams
            for e in train_env + eval_env]
    assert held and not {p for p, _, _ in held} & {p for p, _, _ in train}

    def target(p, c, e):
        s = D.env_scale(envs[e])
        mask = torch.from_numpy(data.gbuffer(p, data._cameras[c]).mask > 0)
        return s, teacher.image(p, c, envs[e]) / s, mask

    def baseline_image(p, c, e):
        tbar = teacher.albedo[None]                  # this teacher's T̄: its uniform albedo
        tex = tbar * teacher.diffuse(p, c, envs[e]) / np.pi
        return composite(list(tex), data.gbuffer(p, data._cameras[c]))

    num, den = torch.zeros(3), torch.zeros(3)
    for p, c, e in train:                            # one LSQ scale per channel
        s, gt, mask = target(p, c, e)
        b = baseline_image(p, c, e) / s
        num += (b * gt)[mask].sum(0)
        den += (b * b)[mask].sum(0)
    scale = num / den

    runs = {}

    def run(student="student", sabotage=None, **overrides):
        """(task, trained model), memoized: tests share a run (they only read it)."""
        key = (student, sabotage, tuple(sorted(overrides.items())))
        if key not in runs:
            runs[key] = _train(student, sabotage, **overrides)
        return runs[key]

    def _train(student, sabotage, **overrides):
        if student == "dram":                  # the presets' DRAM head (texture units)
            overrides = {"lambda_s": DRAM_LAMBDA_S, **overrides}
        cfg = StudentConfig.from_dict({**LEARN, "student": student, **overrides})
        task = D.StudentTask(data, cfg, teacher, envs, train_env, eval_env, names)
        task.evaluate = lambda model, device: {}
        _cached_maps(task.features)
        if sabotage == "zero-features":
            maps = task.features.maps
            task.features.maps = lambda *a: np.zeros_like(maps(*a))
        if sabotage in ("constant", "no-light"):
            wrap = _ConstantDRAM if sabotage == "constant" else _NoLightDRAM
            build = task.build
            task.build = lambda device, resume=None: wrap(build(device, resume))
        result = fit(task, cfg, torch.device("cpu"), show_progress=False)
        model = task.build("cpu")
        model.load_state_dict(result.checkpoint["weights"])
        return task, model.eval()

    @torch.no_grad()
    def score(task, model):
        rows = []
        for p, c, e in held:
            s, gt, mask = target(p, c, e)
            pred = task.render(model, p, c, envs[e], "cpu") / s
            rows.append((float(masked_mse(pred, gt, mask)),
                         float(masked_mse(baseline_image(p, c, e) * scale / s, gt, mask))))
        model_mse, base_mse = np.mean(rows, 0)
        return {"model": float(model_mse), "baseline": float(base_mse)}

    @torch.no_grad()
    def interior(task, model, erode=2):
        """The texture over hand texels ``erode`` texels inside the charts (the model's and
        the teacher's; training pose, first camera, training envs): mean per-channel std of
        each and their correlation."""
        from scipy.ndimage import binary_erosion
        pose, cam = data.train_frames[0].pose, cams[0]
        inner = torch.from_numpy(binary_erosion(data.texels(pose).surfaces[0].inside,
                                                iterations=erode))
        hand = data.hand
        ours, theirs = [], []
        for e in train_env:
            pf = task.features.pose(hand, pose, key=(False, pose))
            feats = task.features.maps(pf, envs[e], data._cameras[cam].center)
            tex = D.student_forward(model, task.config, feats, D.hand_poses(hand, pose), envs[e],
                                    D.wrist_rotations(hand, pose), "cpu")[0]
            s = D.env_scale(envs[e])
            ours.append((tex / s)[:, inner])
            theirs.append((teacher.texture(pose, cam, envs[e])[0] / s)[:, inner])
        std = [float(np.mean([float(t.std(1).mean()) for t in x])) for x in (ours, theirs)]
        a, b = (torch.cat([t - t.mean(1, keepdim=True) for t in x], 1).flatten()
                for x in (ours, theirs))
        corr = float((a * b).sum() / max(float(a.norm() * b.norm()), 1e-30))
        return {"std": std[0], "teacher_std": std[1], "corr": corr, "texels": int(inner.sum())}

    return run, score, interior


def _beats_baseline(scores) -> bool:
    """The learning gate: the student's held-out MSE at most 80 % of the baseline's
    (measured, seeds 0–3: 38–54 %; frozen: ~600 %; zeroed features: 225–270 %)."""
    return scores["model"] <= 0.8 * scores["baseline"]


def test_student_beats_a_strong_baseline_on_held_out_poses(learning):
    run, score, _ = learning
    scores = score(*run())
    assert _beats_baseline(scores), scores


@pytest.mark.parametrize("sabotage", ["frozen", "zero-features"])
def test_sabotaged_student_fails_the_baseline_gate(learning, sabotage):
    """A run that cannot learn (lr 1e-12) or cannot see its features must fail the gate."""
    run, score, _ = learning
    if sabotage == "frozen":
        scores = score(*run(lr=1e-12))
    else:
        scores = score(*run(sabotage="zero-features"))
    assert not _beats_baseline(scores), scores


def test_dram_texture_varies_inside_the_charts(learning):
    """DRAM (codes decoded through untied per-texel biases) learns a spatially varying
    texture that follows the teacher's away from chart borders; the same DRAM made
    spatially constant fails the same floor."""
    run, _, interior = learning

    def varies(r):
        return r["std"] >= DRAM_STD * r["teacher_std"] and r["corr"] >= DRAM_CORR

    live = interior(*run("dram"))
    assert live["texels"] >= 40 and live["teacher_std"] > 0.2, live
    assert varies(live), live
    constant = interior(*run("dram", sabotage="constant"))
    assert not varies(constant), constant


@torch.no_grad()
def _light_response(task, model) -> dict:
    """How DRAM's texture changes between its two training env maps (hand texels, every
    training pose and camera, s-normalized), against the teacher's change: the ratio of
    their RMS and their correlation."""
    from relight_cli.neural import distill as D
    data, hand = task.data, task.data.hand
    ours, theirs = [], []
    for pose, cam in task.items:
        inside = torch.from_numpy(data.texels(pose).surfaces[0].inside)
        tex = []
        for e in task.train_idx:
            denv = task.envs[e]
            s = D.env_scale(denv)
            mine = D.student_forward(model, task.config, None, D.hand_poses(hand, pose), denv,
                                     D.wrist_rotations(hand, pose), "cpu")[0] / s
            tex.append((mine, task.targets.texture(pose, cam, denv)[0] / s))
        ours.append((tex[0][0] - tex[1][0])[:, inside].flatten())
        theirs.append((tex[0][1] - tex[1][1])[:, inside].flatten())
    a, b = torch.cat(ours), torch.cat(theirs)
    return {"ratio": float(a.norm() / b.norm()),
            "corr": float((a * b).sum() / max(float(a.norm() * b.norm()), 1e-30)),
            "explained": float(1 - (a - b).pow(2).sum() / b.pow(2).sum())}


#: the light gate's floors: measured at seeds 0-2, RMS ratio 0.96-0.98 and correlation
#: 0.54-0.58 (the Eq. 11 scale, ``lambda_s`` 25: 0.39-0.74 and 0.36-0.49; light path cut:
#: ratio 4e-8, correlation 0.04)
DRAM_LIGHT_RATIO, DRAM_LIGHT_CORR = 0.8, 0.45


def test_dram_light_path_trains(learning):
    """DRAM's texture follows the light it is given: between its two training env maps its
    texture changes as the teacher's does (RMS ratio and correlation above measured floors).
    The same DRAM given one env code for every map (the light path cut) fails them."""
    run, _, _ = learning

    def follows(r):
        return r["ratio"] >= DRAM_LIGHT_RATIO and r["corr"] >= DRAM_LIGHT_CORR

    live = _light_response(*run("dram"))
    assert follows(live), live
    dead = _light_response(*run("dram", sabotage="no-light"))
    assert not follows(dead), dead


def test_texture_loss_is_the_chart_masked_texture_mse(setup, learning):
    """``loss_space: texture``: the loss is the MSE between the student's and the teacher's
    textures (both ÷ s) over the texels inside the UV charts (the texel G-buffer's, every
    hand), summed with nothing image-side; ``image`` (the paper's) differs from it."""
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    task, _ = learning[0]("student")
    data, hand = task.data, task.data.hand
    for student in ("student", "dram"):
        cfg = StudentConfig.from_dict({**LEARN, "student": student, "loss_space": "texture",
                                       "lambda_neg": 0.0})
        t = D.StudentTask(data, cfg, task.targets, task.envs, task.train_idx, task.eval_idx,
                          task.env_names)
        torch.manual_seed(3)
        net = t.build("cpu")
        pose, cam = t.items[0]
        denv = t.env_for(0, t.items[0])
        with torch.no_grad():
            parts = t.loss(net, t.items[0], 0, "cpu")[1]
            feats = None
            if student == "student":
                pf = t.features.pose(hand, pose, key=(False, pose))
                feats = t.features.maps(pf, denv, data._cameras[cam].center)
            tex = D.student_forward(net, cfg, feats, D.hand_poses(hand, pose), denv,
                                    D.wrist_rotations(hand, pose), "cpu")
            s = D.env_scale(denv)
            target = task.targets.texture(pose, cam, denv)
            assert len(tex) == len(target) == data.texels(pose).n_hands
            err = []
            for k in range(len(tex)):
                inside = torch.from_numpy(data.texels(pose).surfaces[k].inside)
                err.append(((tex[k] - target[k]) / s)[:, inside].flatten())
            want = float(torch.cat(err).pow(2).mean())
            assert abs(parts["mse"] - want) <= 1e-5 * want and want > 0, (parts, want)
            image_cfg = StudentConfig.from_dict({**cfg.to_dict(), "loss_space": "image"})
            ti = D.StudentTask(data, image_cfg, task.targets, task.envs, task.train_idx,
                               task.eval_idx, task.env_names)
            assert abs(ti.loss(net, t.items[0], 0, "cpu")[1]["mse"] - want) > 1e-3 * want


#: the texture loss's light gate: the share of the teacher's texture change between the
#: two training maps that DRAM's change explains, 1 − |a − b|²/|b|².  Measured at seeds
#: 0-2: 0.54-0.56 with ``loss_space: texture`` (ratio 0.67-0.88, correlation 0.73-0.76);
#: the image loss: 0.10-0.22 (ratio 0.89-0.97, correlation 0.54-0.57); light path cut: 0
DRAM_TEXTURE_EXPLAINED = 0.4


def test_dram_light_path_trains_on_the_texture_loss(learning):
    """Supervised on its whole texture (``loss_space: texture``), DRAM's texture change
    between its two training maps explains most of the teacher's (above a measured floor
    the image loss does not reach); with its light path cut it explains none of it."""
    run, _, _ = learning
    live = _light_response(*run("dram", loss_space="texture"))
    assert live["explained"] >= DRAM_TEXTURE_EXPLAINED, live
    dead = _light_response(*run("dram", sabotage="no-light", loss_space="texture"))
    assert dead["explained"] < DRAM_TEXTURE_EXPLAINED, dead


# ---------------------------------------------------------------- held-out segment


def test_distill_trains_on_no_held_out_pose(setup):
    """No distill training item's pose is a held-out frame's, nor any frame's at or
    after the held-out segment's start (fully lit frames interleave with it)."""
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    from relight_cli.neural.data import CaptureData

    def leaks(data, task):
        start = data.heldout_frames[0]
        late = {f.pose for f in data.capture.frames
                if (f.time, f.index) >= (start.time, start.index)}
        late |= {f.pose for f in data.heldout_frames}
        return sorted({p for p, _ in task.items} & late)

    cfg = StudentConfig.from_dict(STUDENT)
    checked = 0
    for holdout in (0.25, 0.5, 0.75):
        data = CaptureData(str(setup / "cap"), 16, 1, holdout=holdout)
        task = D.StudentTask(data, cfg, None, [], [0], [], ["x"])
        assert task.items and leaks(data, task) == [], holdout
        # a fully lit frame after the segment's start exists here: the gate can fail
        if any((f.time, f.index) > (data.heldout_frames[0].time, data.heldout_frames[0].index)
               for f in data.fully_lit_frames):
            checked += 1
            data.train_fully_lit_frames = data.fully_lit_frames      # the old, leaking split
            assert leaks(data, D.StudentTask(data, cfg, None, [], [0], [], ["x"]))
    assert checked


@pytest.mark.parametrize("untied", [0, 24])
def test_student_untied_biases_give_spatial_capacity(untied):
    """With zero features (nothing spatial in), only untied per-texel biases let the
    student fit a spatially varying texture; the tied student stays constant inside
    (away from the zero padding's reach: 2 pose-encoder convs, 2 decoder convs and the
    head, 5 texels)."""
    from relight_cli.neural.student import StudentNet
    torch.manual_seed(0)
    net = StudentNet(3, (8, 8), 6, (4, 4), untied=untied)
    target = torch.rand(1, 3, 24, 24) * 0.3
    features, pose = torch.zeros(1, 3, 24, 24), torch.zeros(1, 6)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(300):
        opt.zero_grad()
        loss = ((net(features, pose) - target) ** 2).mean()
        loss.backward()
        opt.step()
    inner = net(features, pose)[..., 6:-6, 6:-6].detach()
    spread = float(inner.std(dim=(-2, -1)).max())          # over texels, per channel
    if untied:
        assert spread > 0.5 * float(target[..., 6:-6, 6:-6].std(dim=(-2, -1)).min())
        assert loss.item() < 0.3 * float(target.var())
    else:
        assert spread < 1e-5


def test_dram_film_scale_is_bounded():
    """DRAM's FiLM multiplies each layer by 1 + tanh(a) ∈ (0, 2) however large its
    linear map of the light code makes a: the unbounded 1 + a let one Adam step scale the
    texture by orders of magnitude (both converged-study DRAM rows blew up mid-run)."""
    from relight_cli.neural.student import DRAMNet
    torch.manual_seed(0)
    net = DRAMNet(8 * 16 * 3, [8, 8, 8], 6, (4, 4), code=16, tex_res=16)
    cond = torch.randn(3, 16 + 6) * 10
    h = torch.ones(3, 8, 4, 4)
    for i, film in enumerate(net.film):
        with torch.no_grad():
            film.weight.normal_(0, 100.0)
            film.bias.zero_()
            film.weight[film.out_features // 2:] = 0     # no shift: the scale alone
        out = net._film(h[:, :film.out_features // 2], i, cond)
        assert torch.isfinite(out).all()
        assert out.min() >= 0 and out.max() <= 2, (i, float(out.min()), float(out.max()))
        assert out.max() > 1.5 and out.min() < 0.5       # the bound is reached, not forced


# ---------------------------------------------------------------- the linear head


def test_linear_head_learns_and_fails_without_features(learning):
    """``head: linear`` (per-texel weights of the features, from the pose alone) passes
    the learning gate; fed zeroed features it cannot: its texture is then 0 whatever the
    weights, every gradient vanishes and the trainer stops the run as collapsed."""
    from relight_cli.neural.train import TrainingCollapsed
    run, score, _ = learning
    assert _beats_baseline(score(*run(head="linear"))), "linear head"
    with pytest.raises(TrainingCollapsed):
        run(head="linear", sabotage="zero-features")


def test_linear_head_least_squares_start_is_the_closed_form(learning):
    """``head_init: lsq`` sets the weights to the per-texel least-squares fit before any
    step: this pseudo ground truth is ρ/π · diffuse + 0.5 · phong16, a linear map of the
    features, so the fit alone (lr 1e-12: no step moves it) scores far below the
    baseline and a grey start does not; on texels the features reach, its weights match
    np.linalg.lstsq of the same samples stacked (an independent solve)."""
    from relight_cli.neural import distill as D
    run, score, _ = learning
    task, model = run(head="linear", head_init="lsq", lr=1e-12)
    fitted = score(task, model)
    grey = score(*run(head="linear", lr=1e-12))
    assert fitted["model"] < 0.05 * fitted["baseline"], fitted
    assert not _beats_baseline(grey), grey
    # the same samples, stacked: rows of every training (pose, camera) under its drawn map
    cfg, n, k = task.config, task.config.tex_res, model.maps
    rows, targets = [], []
    for npass in range(D.LSQ_PASSES):
        rng = np.random.default_rng([int(cfg.seed), 17, npass])
        for pose, cam in task.items:
            denv = task.env_for(0, (pose, cam), rng)
            s = D.env_scale(denv)
            pf = task.features.pose(task.data.hand, pose, key=(False, pose))
            f = task.features.maps(pf, denv, task.data._cameras[cam].center)[0] / s
            rows.append(f.reshape(k, 3 * n * n).T.astype(np.float64))
            targets.append(task.targets.texture(pose, cam, denv)[0].numpy().reshape(-1) / s)
    rows, targets = np.stack(rows, 1), np.stack(targets, 1)         # [3N², S, K], [3N², S]
    w = model.weight_bias.detach().numpy().reshape(k, 3 * n * n).T
    # the ridge: √λ·I rows pulling towards the grey start W₀ (0.5 on diffuse, 0 else)
    ridge = D.LSQ_RIDGE * float((rows ** 2).sum()) / (3 * n * n * k)
    start = np.zeros(k)
    start[0] = 0.5
    strong = np.argsort(-np.abs(rows).sum((1, 2)))[:50]
    for x in [*strong, int(np.argmin(np.abs(rows).sum((1, 2))))]:     # and the emptiest
        a = np.concatenate([rows[x], np.sqrt(ridge) * np.eye(k)])
        ref = np.linalg.lstsq(a, np.concatenate([targets[x], np.sqrt(ridge) * start]),
                              rcond=None)[0]
        assert np.allclose(w[x], ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max()), (x, w[x], ref)


def test_linear_head_is_linear_in_the_env_map(setup, tmp_path):
    """The linear head's texture is ReLU(Σ_k W_k(θ) ⊙ F_k) with weights that see no
    light: wherever it is not clipped (raw ≥ 0 under both maps), the texture under env
    a + b is the sum of those under a and b, to float rounding; DRAM's (its light code is
    log1p of the map) is not.  (The eq11 student, near-linear this early in training,
    misses by only ~1e-4: no control.)"""
    from relight_cli.envmap import DiscreteEnv
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import StudentConfig
    from relight_cli.neural.data import CaptureData

    (tmp_path / "lin.json").write_text(json.dumps({**STUDENT, "head": "linear"}))
    (tmp_path / "dram.json").write_text(json.dumps({**STUDENT, "student": "dram"}))
    data = CaptureData(str(setup / "cap"), 16, 1)
    gaps = {}
    for head, config in (("linear", tmp_path / "lin.json"), ("dram", tmp_path / "dram.json")):
        r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config", config,
                    "--iters", "20", "-q", "-o", tmp_path / f"{head}.pt")
        assert r.exit_code == 0, r.output
        model, cfg = student_model(read_checkpoint(str(tmp_path / f"{head}.pt")))
        assert isinstance(cfg, StudentConfig) and head in (cfg.head, cfg.student)
        a = _sky(*cfg.env_res)
        rng = np.random.default_rng(0)
        b = DiscreteEnv(a.directions, a.solid_angle,
                        rng.uniform(0, 30, a.radiance.shape).astype(a.radiance.dtype),
                        a.height, a.width, "noise")
        both = DiscreteEnv(a.directions, a.solid_angle, a.radiance + b.radiance, a.height,
                           a.width, "sum")
        task = D.StudentTask(data, cfg, None, [a], [0], [], ["sky"])
        pose, cam = task.items[0]
        pf = task.features.pose(data.hand, pose, key=(False, pose))
        out = []
        for env in (a, b, both):
            feats = task.features.maps(pf, env, data._cameras[cam].center)
            with torch.no_grad():
                tex, raw, s = D.student_forward(model, cfg, feats, D.hand_poses(data.hand, pose),
                                                env, D.wrist_rotations(data.hand, pose), "cpu",
                                                return_raw=True)
            out.append((tex[0], raw[0]))
        (ta, ra), (tb, rb), (tab, _) = out
        kept = (ra >= 0) & (rb >= 0)
        assert float(kept.float().mean()) > 0.5, head
        gaps[head] = float((tab - ta - tb)[kept].abs().max() / tab.abs().max())
    assert gaps["linear"] < 1e-5, gaps
    assert gaps["dram"] > 1e-2, gaps


def test_closed_form_student_from_the_command_line(setup, tmp_path):
    """``--iters 0`` with ``head_init: lsq``: the least-squares fit is the student — a
    checkpoint at step 0 that validates, resumes into SGD, and renders."""
    from relight_cli.neural.checkpoints import read_checkpoint
    (tmp_path / "lsq.json").write_text(json.dumps({**STUDENT, "head": "linear",
                                                   "head_init": "lsq"}))
    out = tmp_path / "lsq.pt"
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--config",
                tmp_path / "lsq.json", "--iters", "0", "--metrics-out", tmp_path / "v.json",
                "-q", "-o", out)
    assert r.exit_code == 0, r.output
    ckpt = read_checkpoint(str(out))
    assert ckpt["step"] == 0
    grey = torch.zeros_like(ckpt["weights"]["weight_bias"])
    grey[:, :3] = 0.5
    assert not torch.equal(ckpt["weights"]["weight_bias"], grey)        # the fit moved it
    record = json.loads((tmp_path / "v.json").read_text())
    assert np.isfinite(record["metrics"]["vs_teacher"]["psnr"])
    r = _invoke("distill", setup / "teacher.pt", setup / "cap", *ENVS, "--resume", out,
                "--iters", "2", "-q", "-o", tmp_path / "more.pt")
    assert r.exit_code == 0, r.output
    assert read_checkpoint(str(tmp_path / "more.pt"))["step"] == 2
    img = tmp_path / "img.exr"
    r = _invoke("relight", setup / "cap" / "hand.npz", "builtin:sky", "--model", "student",
                "--checkpoint", out, "--size", "24x24", "-q", "-o", img)
    assert r.exit_code == 0 and img.is_file(), r.output
