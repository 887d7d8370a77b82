"""relight_cli.jobs.synth_capture called without click: the light stage's arrays and the folder
it writes equal what ``relight synth-capture`` writes."""

from __future__ import annotations

import json

import numpy as np

from relight_cli.cli import inputs as I


def _cli(run_cli, *args):
    r = run_cli(*args)
    assert r.exit_code == 0, r.output
    return r


# ---------------------------------------------------------------- synth-capture


def test_light_stage_job_equals_the_cli(run_cli, tmp_path):
    """The job's plan (key, frames, lit LEDs, recorded settings) and its renders are what
    synth-capture writes (images are half floats)."""
    from relight_cli.formats import capture as C
    from relight_cli.jobs import synth_capture as J

    out = tmp_path / "cap"
    _cli(run_cli, "synth-capture", "-o", out, "--cameras", "2", "--leds", "6", "--group", "2",
         "--n-frames", "2", "--full-every", "2", "--size", "10", "--tex-res", "32", "--aa", "1",
         "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs", "builtin:sky",
         "--eval-env-res", "16x8", "--seed", "2", "-q")
    settings = J.StageSettings(cameras=2, lights=6, group=2, frames=2, full_every=2, res=10,
                               tex_res=32, aa=1, seed=2, eval_env_res=(8, 16))
    stage = J.light_stage(I.load_hand("builtin:right"), [I.load_envmap("builtin:sky")],
                          settings, eval_poses=1)
    cap = C.read_capture(str(out))
    assert stage.key == cap.key and json.loads(json.dumps(stage.record)) == cap.settings
    assert [f.lights_on for f in stage.plan.frames] == [f.lights_on for f in cap.frames]
    assert stage.plan.frames[1].lit == "group"
    frame = stage.plan.frames[1]
    renders = list(stage.frame(frame, stage.plan.cameras[1:]))
    assert [r.camera.name for r in renders] == ["cam001"] and renders[0].hand_masks is None
    rgb, mask = C.read_image(str(out / C.image_path(1, "cam001")))
    np.testing.assert_array_equal(rgb, renders[0].image.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(mask, renders[0].mask.astype(np.float16).astype(np.float32))
    assert renders[0].mask.mean() > 0.01
    [held] = stage.held_out(0, 0, stage.plan.cameras[:1])
    rgb, _ = C.read_image(str(out / cap.evaluation["renders"][0]["image"]))
    np.testing.assert_array_equal(rgb, held.image.astype(np.float16).astype(np.float32))
    assert not np.allclose(held.image, renders[0].image)


def test_make_capture_writes_the_clis_folder(run_cli, tmp_path):
    """``jobs.synth_capture.make_capture`` (what the studies call) writes the folder
    ``synth-capture`` writes: the same files, index (but the provenance's command line,
    empty from Python) and pixels; a second call resumes and renders nothing."""
    from relight_cli.formats import capture as C
    from relight_cli.jobs import synth_capture as J

    args = dict(cameras=2, lights=6, group=2, frames=3, res=10, tex_res=32, aa=1, seed=4,
                eval_poses=1, eval_cameras=1, eval_envs=["builtin:sky"], eval_env_res=(8, 16))
    cli_out, lib_out = tmp_path / "cli", tmp_path / "lib"
    _cli(run_cli, "synth-capture", "builtin:two", "-o", cli_out, "--cameras", "2", "--leds",
         "6", "--group", "2", "--n-frames", "3", "--size", "10", "--tex-res", "32", "--aa", "1",
         "--seed", "4", "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs",
         "builtin:sky", "--eval-env-res", "16x8", "-q")
    capture, rendered, skipped = J.make_capture(str(lib_out), "builtin:two", **args)
    assert (rendered, skipped) == (3 * 2 + 1, 0)
    files = sorted(p.relative_to(cli_out) for p in cli_out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(lib_out) for p in lib_out.rglob("*") if p.is_file())

    def index(folder):
        obj = json.loads((folder / C.INDEX).read_text())
        return obj, obj["provenance"].pop("command")
    (lib, lib_command), (cli, cli_command) = index(lib_out), index(cli_out)
    assert lib == cli and lib_command == ""      # (the CLI run before it has ended)
    assert cli_command.startswith("relight synth-capture builtin:two -o ")
    for rel in files:
        if rel.suffix == ".exr" and rel.parts[:2] != ("eval", "envs"):
            for a, b in zip(C.read_image(str(cli_out / rel)), C.read_image(str(lib_out / rel))):
                np.testing.assert_array_equal(a, b)
    assert J.make_capture(str(lib_out), "builtin:two", **args)[1:] == (0, 3 * 2 + 1)
