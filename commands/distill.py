"""``relight distill``: RelightableHands' student (or the DRAM baseline) from teacher renders."""

from __future__ import annotations

import click

from relight_cli.cli.tools import log, no_clobber_option, quiet_option

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
              help="tiny: 32² maps, ~150 iterations, minutes on a CPU, far from converged "
                   "(tests, demo; 315 s on the demo capture, 2 shared CPU cores); cpu: 64² "
                   "maps, the "
                   "student's head linear in its features (ours; config head eq11: the "
                   "paper's), 4000 iterations with a cosine learning-rate decay, 10-30 min "
                   "on 2 CPU cores (benchmarks/results/converged/student_linear/); paper: "
                   "RelightableHands' sizes and head (100k iterations: a GPU job).")
@click.option("--config", "config_file", default=None, metavar="FILE.json",
              help="JSON object of config fields overriding the preset (formats/checkpoint.md; "
                   "'-': stdin).")
@click.option("--iters", type=int, default=None,
              help="Adam iterations (overrides the preset); 0 with the config's head_init "
                   "lsq: the closed-form least-squares student alone.")
@click.option("--env-res", default=None, metavar="WxH",
              help="Lat-long directions each env map is discretized into: the student's "
                   "features and the teacher's pseudo ground truth (one teacher pass per "
                   "direction) [preset: 32x16, the paper's 16×32 grid]. Fewer is faster.")
@click.option("--no-specular", is_flag=True, help="Ablation (Table 2): diffuse features only.")
@click.option("--no-visibility", is_flag=True,
              help="Ablation (Table 2): features baked without visibility.")
@click.option("--cache", "cache_dir", default=None, metavar="DIR",
              help="Folder for the teacher's per-direction textures beyond the memory budget "
                   "(config cache_mb, 2048 MB); without it they are recomputed, one teacher "
                   "pass per missed sample (the log says when the budget is short).")
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

    from . import _learned as L

    # ---- options (usage errors, before any work)
    specs, n_eval, names, env_res = _check_usage(teacher, capture, env_specs, eval_specs, output,
                                                 iters, config_file, vgg_weights, resume,
                                                 metrics_out, cache_dir, env_res, no_clobber)

    import torch  # noqa: F401

    from relight_cli.cli.inputs import load_envmap
    from relight_cli.formats.checkpoint import write_checkpoint
    from relight_cli.jobs import distill as job
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.provenance import file_sha256, provenance

    # ---- inputs (data errors), the job, the outputs (rank 0 writes)
    config, ckpt, torch_device = _configure(preset, config_file, resume, device, student, iters,
                                            seed, env_res, no_specular, no_visibility)
    tck = job.load_teacher(read_checkpoint(teacher, kind="teacher"), torch_device,
                           file_sha256(teacher), teacher)
    data = L.read_captures([capture], tck.config)[0]
    envs = {name: load_envmap(spec) for name, spec in zip(names, specs)}
    rank = int(os.environ.get("RANK", "0"))
    quiet = quiet or rank != 0
    options = job.Options(config, preset, torch_device, L.read_vgg(vgg_weights, torch_device),
                          ckpt, resume, progress=not quiet, n_eval=n_eval, cache_dir=cache_dir)
    inputs = {"teacher": teacher, "capture": data.index_path,
              **{f"env{k}": spec for k, spec in enumerate(specs)},
              **L.file_inputs(vgg_weights, resume, config_file)}
    trained = job.run(tck, data, envs, options,
                      provenance=lambda s: provenance("relight/checkpoint", 1, inputs, s),
                      save=L.saver(output) if rank == 0 else None, log=lambda m: log(m, quiet),
                      names={"capture": capture, "teacher": teacher, "envs": ", ".join(env_specs)})
    if rank != 0:
        return
    write_checkpoint(output, trained.result.checkpoint)
    L.write_validation(metrics_out, trained.result, {"teacher": teacher, "capture":
                       data.index_path}, trained.config, trained.record)
    log(f"wrote {output}: " + job.summary(trained), quiet)


def _check_usage(teacher, capture, env_specs, eval_specs, output, iters, config_file, vgg_weights,
                 resume, metrics_out, cache_dir, env_res, no_clobber):
    """The options' usage errors (exit 2), before any work: (every env map, training ones
    first; how many are for evaluation only; their names; --env-res as the config's
    (H, W) or None)."""
    import os

    from relight_cli.cli.inputs import env_grid
    from relight_cli.cli.tools import check_input
    from relight_cli.errors import UsageProblem

    from . import _learned as L

    if iters is not None and iters < 0:
        raise UsageProblem(f"--iters must be ≥ 0 (0: only with head_init lsq), got {iters}")
    L.check_capture(capture, index_ok=False)
    check_input(teacher)
    L.check_inputs(config_file, vgg_weights, resume)
    train_specs, held_specs = _expand_envs(env_specs), _expand_envs(eval_specs)
    specs = train_specs + held_specs
    for spec in specs:
        check_input(spec)
    L.check_outputs(output, metrics_out, no_clobber)
    if cache_dir is not None and os.path.exists(cache_dir) and not os.path.isdir(cache_dir):
        raise UsageProblem("--cache must be a folder", cache_dir)
    names = [_env_name(s) for s in specs]
    if len(set(names)) != len(names):
        raise UsageProblem("two --envs maps have the same name")
    env_res = None if env_res is None else tuple(env_grid(env_res))   # the config's (H, W)
    return specs, len(held_specs), names, env_res


def _configure(preset, config_file, resume, device, student, iters, seed, env_res, no_specular,
               no_visibility):
    """(the StudentConfig, the read --resume checkpoint or None, the torch device), from
    the inputs (data errors)."""
    from relight_cli.jobs import distill as job
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.train import resolve_device

    ckpt = read_checkpoint(resume, kind="student") if resume is not None else None
    config = job.configure(preset, config_file, {
        "student": student, "iters": iters, "seed": seed, "env_res": env_res,
        "specular": False if no_specular else None,
        "visibility": False if no_visibility else None}, ckpt, resume)
    return config, ckpt, resolve_device(device)


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
