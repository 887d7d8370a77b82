"""``relight distill``: RelightableHands' student (or the DRAM baseline) from teacher renders."""

from __future__ import annotations

import click

from relight_cli.clitools import log, no_clobber_option, quiet_option

from ._learned import training_options


@click.command("distill",
               short_help="Distill a fast env-map student (or DRAM) from a trained teacher.")
@click.argument("teacher", metavar="TEACHER.pt")
@click.argument("capture", metavar="CAPTURE")
@click.option("--envs", "env_specs", multiple=True, required=True, metavar="ENV",
              help="Env maps to learn from (repeatable; files or builtin:NAME, or a folder of "
                   ".exr/.hdr files). A seeded env_holdout share is kept for evaluation only.")
@click.option("--eval-envs", "eval_specs", multiple=True, metavar="ENV",
              help="Env maps for evaluation only (repeatable, as --envs): a fixed split; then "
                   "every --envs map trains and env_holdout is not used.")
@click.option("-o", "--output", required=True, metavar="STUDENT.pt",
              help="Checkpoint to write (relight/checkpoint, kind student).")
@click.option("--student", type=click.Choice(["student", "dram"]), default=None,
              help="student: texel-aligned features (App. A.2); dram: the bottleneck "
                   "hypernetwork baseline (App. A.3) [default: student].")
@click.option("--preset", type=click.Choice(["tiny", "cpu", "paper"]), default="tiny",
              show_default=True,
              help="tiny: 32² maps, minutes on a CPU (tests, demo); cpu: 64² maps, 4000 "
                   "iterations with a cosine learning-rate decay, about 30 min on 2 CPU "
                   "cores (benchmarks/results/presets.md); paper: RelightableHands' sizes "
                   "(100k iterations: a GPU job).")
@click.option("--config", "config_file", default=None, metavar="FILE.json",
              help="JSON object of config fields overriding the preset (formats/checkpoint.md; "
                   "'-': stdin).")
@click.option("--iters", type=int, default=None, help="Adam iterations (overrides the preset).")
@click.option("--env-res", default=None, metavar="WxH",
              help="Lat-long directions each env map is discretized into: the student's "
                   "features and the teacher's pseudo ground truth (one teacher pass per "
                   "direction) [preset: 32x16, the paper's 16×32 grid]. Fewer is faster.")
@click.option("--no-specular", is_flag=True, help="Ablation (Table 2): diffuse features only.")
@click.option("--no-visibility", is_flag=True,
              help="Ablation (Table 2): features baked without visibility.")
@click.option("--cache", "cache_dir", default=None, metavar="DIR",
              help="Folder for the teacher's per-direction textures beyond the memory budget "
                   "(config cache_mb); without it they are recomputed.")
@training_options("held-out poses × evaluation env maps against the teacher and against ground truth")
@no_clobber_option
@quiet_option
def command(teacher, capture, env_specs, eval_specs, output, student, preset, config_file, iters,
            env_res, no_specular, no_visibility, cache_dir, vgg_weights, resume, device, metrics_out, seed,
            no_clobber, quiet):
    """Distill RelightableHands' student from TEACHER.pt (train-teacher) on CAPTURE's
    poses and cameras under the --envs maps, and write the checkpoint -o.

    The teacher's per-direction textures (32x16 directions, each with its own
    visibility) are computed once per pose and camera, so every env map's target
    is their weighted sum (linearity of light transport).  The student sees
    bake-features' texel maps of the pose under the env map (diffuse + Phong
    16/32/64, visibility traced once per pose) and the joint features, and
    predicts the texture (App. A.2, Eq. 11), rendered into each camera and
    compared with the teacher's render (Eq. 5).  Training maps are augmented by
    exact rotations about +Y.  Relight with: relight relight HAND ENV --model
    student --checkpoint STUDENT.pt.

    \b
    Examples:
      relight distill teacher.pt capture/ --envs builtin:sky --envs builtin:studio \\
          --envs builtin:uniform -o student.pt
      relight distill teacher.pt capture/ --envs hdris/ --student dram -o dram.pt
    """
    import os

    from relight_cli.clitools import check_input
    from relight_cli.errors import DataError, UsageProblem

    from ._learned import check_outputs, write_validation

    # ---- usage checks before any work
    if iters is not None and iters < 1:
        raise UsageProblem(f"--iters must be ≥ 1, got {iters}")
    if not os.path.isdir(capture):
        raise DataError("CAPTURE must be a capture folder (with capture.json)", capture)
    if os.path.isfile(os.path.join(capture, "capture.json")):
        check_input(os.path.join(capture, "capture.json"))
    check_input(teacher)
    for path, role in ((config_file, "--config"), (vgg_weights, None), (resume, None)):
        if path is not None:
            check_input(path, stdin=role)
    train_specs = _expand_envs(env_specs)
    held_specs = _expand_envs(eval_specs)
    specs = train_specs + held_specs
    for spec in specs:
        check_input(spec)
    check_outputs(output, metrics_out, no_clobber)
    if cache_dir is not None and os.path.exists(cache_dir) and not os.path.isdir(cache_dir):
        raise UsageProblem("--cache must be a folder", cache_dir)
    names = [_env_name(s) for s in specs]
    if len(set(names)) != len(names):
        raise UsageProblem("two --envs maps have the same name")

    import torch  # noqa: F401

    from relight_cli.features import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint, write_checkpoint
    from relight_cli.neural import distill as D
    from relight_cli.neural.config import (STUDENT_PRESETS, StudentConfig, resolve_config,
                                           resume_config)
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.checkpoints import teacher_model
    from relight_cli.neural.train import fit, resolve_device
    from relight_cli.provenance import file_sha256, outside_transaction, provenance

    from relight_cli.inputs import load_envmap

    if env_res is not None:
        from relight_cli.inputs import env_grid
        env_res = tuple(env_grid(env_res))           # the config stores (H, W)
    overrides = {"student": student, "iters": iters, "seed": seed, "env_res": env_res,
                 "specular": False if no_specular else None,
                 "visibility": False if no_visibility else None}
    ckpt = None
    if resume is not None:
        ckpt = read_checkpoint(resume, kind="student")
        config = resume_config(ckpt, StudentConfig, overrides, config_file, iters, resume)
    else:
        config = resolve_config(preset, config_file, overrides, presets=STUDENT_PRESETS,
                                config_class=StudentConfig)
    torch_device = resolve_device(device)

    # ---- inputs (data errors)
    tck = read_checkpoint(teacher, kind="teacher")
    try:
        teacher_net, tconfig, mean_texture = teacher_model(tck, torch_device)
    except (ValueError, UsageProblem) as exc:
        raise DataError(getattr(exc, "message", str(exc)), teacher) from None
    data = CaptureData(capture, tconfig.tex_res, tconfig.aa, tconfig.visibility, tconfig.falloff,
                       tconfig.holdout, tconfig.cache_poses)
    if tck["capture_key"] != data.key:
        log(f"note: the teacher was trained on another capture (key {tck['capture_key']}); "
            f"distilling on this one", quiet)
    if ckpt is not None and ckpt["capture_key"] != data.key:
        raise DataError("checkpoint was distilled on another capture", resume)
    if (data.hand.n_joints - 1) * 3 != int(tck["pose_dim"]):
        raise DataError("the capture's hand does not match the teacher's joints", teacher)
    envs = []
    for spec in specs:
        env = load_envmap(spec)
        envs.append(discretize_env(env, *config.env_res))
    if held_specs:
        train_idx = list(range(len(train_specs)))
        eval_idx = list(range(len(train_specs), len(specs)))
    else:
        train_idx, eval_idx = D.split_envs(names, config.env_holdout, config.seed,
                                           ", ".join(env_specs))
    if ckpt is not None:
        import json
        saved = json.loads(ckpt.get("extra", {}).get("envs", "{}") or "{}")
        if saved and saved.get("train") != [names[i] for i in train_idx]:
            raise UsageProblem("--resume needs the same --envs as the run it continues")
    grid = envs[0]
    teacher_digest = file_sha256(teacher)
    targets = D.TeacherTargets(teacher_net, tconfig, data, grid, cache_dir, config.cache_mb,
                               torch_device, mean_texture, identity=teacher_digest)
    vgg = None
    if vgg_weights is not None:
        from relight_cli.neural.losses import load_vgg
        vgg = load_vgg(vgg_weights).to(torch_device)
    elif ckpt is None:
        config.lambda_vgg = 0.0
    task = D.StudentTask(data, config, targets, envs, train_idx, eval_idx, names, vgg,
                         teacher_digest)
    rank = int(os.environ.get("RANK", "0"))
    quiet = quiet or rank != 0
    log(f"read {capture}: {len(task.items)} (pose, camera) pairs; {len(train_idx)} training and "
        f"{len(eval_idx)} evaluation env map(s); student {config.student}, {config.tex_res}² "
        f"features, {config.iters} iterations on {torch_device}; pseudo ground truth "
        f"{_texture_mb(data, tconfig, grid):.1f} MB per pose and camera", quiet)
    inputs = {"teacher": teacher, "capture": data.index_path}
    for k, spec in enumerate(specs):
        inputs[f"env{k}"] = spec
    for role, path in (("vgg_weights", vgg_weights), ("resume", resume), ("config", config_file)):
        if path is not None:
            inputs[role] = path
    record = provenance("relight/checkpoint", 1, inputs, {"preset": preset, **config.to_dict()})

    def save(checkpoint):
        with outside_transaction():
            write_checkpoint(output, checkpoint)

    from relight_cli.neural.train import _summary
    result = fit(task, config, torch_device, resume=ckpt, provenance=record,
                 save=save if rank == 0 else None, show_progress=not quiet,
                 log=lambda m: log(m, quiet))
    if rank != 0:
        return
    write_checkpoint(output, result.checkpoint)
    write_validation(metrics_out, result, {"teacher": teacher, "capture": data.index_path},
                     config, record)
    its = result.steps_run / result.seconds if result.seconds > 0 else float("inf")
    log(f"wrote {output}: {result.steps_run} step(s) in {result.seconds:.1f} s ({its:.2f} it/s); "
        f"{targets.computed} teacher texture set(s) computed; "
        + _summary(result.history[-1] if result.history else {"step": config.iters}), quiet)


def _texture_mb(data, tconfig, grid) -> float:
    return data.n_hands * len(grid.directions) * 3 * tconfig.tex_res ** 2 * 4 / 2 ** 20


def _env_name(spec: str) -> str:
    import os
    if spec.startswith("builtin:"):
        return spec.split(":", 1)[1]
    base = os.path.basename(spec)
    return base.split(".", 1)[0] or base


def _expand_envs(specs) -> list[str]:
    """Files and builtin: names as given; a folder stands for its .exr/.hdr files (sorted)."""
    import os
    out = []
    for spec in specs:
        if not spec.startswith("builtin:") and os.path.isdir(spec):
            found = sorted(os.path.join(spec, f) for f in os.listdir(spec)
                           if f.lower().endswith((".exr", ".hdr")))
            if not found:
                from relight_cli.errors import DataError
                raise DataError("folder holds no .exr/.hdr env maps", spec)
            out += found
        else:
            out.append(spec)
    return out
