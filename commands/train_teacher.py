"""``relight train-teacher``: RelightableHands' OLAT teacher (or its GGX baseline), or URHand's
linear model, from a capture."""

from __future__ import annotations

import click

from relight_cli.clitools import SquareSize, log, no_clobber_option, quiet_option

from ._learned import training_options


@click.command("train-teacher",
               short_help="Train the OLAT teacher, its GGX baseline or URHand's linear model "
                          "on a capture.")
@click.argument("captures", metavar="CAPTURE...", nargs=-1, required=True)
@click.option("-o", "--output", required=True, metavar="TEACHER.pt",
              help="Checkpoint to write (relight/checkpoint, formats/checkpoint.md).")
@click.option("--preset", type=click.Choice(["tiny", "cpu", "paper"]), default="tiny",
              show_default=True,
              help="tiny: 32² texture, ~150 iterations, seconds to minutes (tests, demo); "
                   "cpu: 64² texture, 6000 iterations with a cosine learning-rate decay, "
                   "about 15-30 min on 2 CPU cores (benchmarks/results/presets.md says how "
                   "close each model comes to its ceiling); paper: the papers' sizes and "
                   "iterations (100k teacher, 2M linear model: a GPU job).")
@click.option("--config", "config_file", default=None, metavar="FILE.json",
              help="JSON object of config fields overriding the preset (see "
                   "formats/checkpoint.md; '-': stdin).")
@click.option("--model", type=click.Choice(["olat", "ggx", "linear"]), default=None,
              help="olat: the neural OLAT teacher (App. A.1); ggx: the physically based "
                   "baseline (App. B, Eq. 12); linear: URHand's linear lighting model with "
                   "its physical branch (Sec. 4) [default: olat].")
@click.option("--iters", type=int, default=None, help="Adam iterations (overrides the preset).")
@click.option("--batch", type=int, default=None, help="Samples (frame × camera) per step and rank.")
@click.option("--lr", type=float, default=None, help="Adam learning rate.")
@click.option("--tex-res", type=SquareSize(), default=None,
              help="Texture size N (or NxN) of the U-Net.")
@click.option("--no-visibility", is_flag=True,
              help="Ablation (RelightableHands Table 1): no ray-traced visibility input.")
@click.option("--light-path", type=click.Choice(["linear", "nonlinear", "mlp"]), default=None,
              help="[linear] Ablations (URHand Table 2): nonlinear puts LeakyReLU on the light "
                   "path; mlp is the holistic baseline (supp. 10.2: a 32x16 lighting map "
                   "through one bias-free linear layer) [default: linear].")
@click.option("--linearity-loss", type=float, default=None, metavar="λ",
              help="[linear] Eq. 17's linearity consistency weight (with --light-path "
                   "nonlinear).")
@click.option("--features", "light_features", type=click.Choice(["pbr", "phong"]), default=None,
              help="[linear] Shading features: pbr (Eq. 10-15) or phong (Table 3) "
                   "[default: pbr].")
@click.option("--no-specular", is_flag=True, help="[linear] Ablation: no specular feature.")
@click.option("--no-refiner", is_flag=True,
              help="[linear] Ablation: coarse normals (no displacement map).")
@training_options("held-out poses, fully lit frames, env-map ground truth, per validation step")
@no_clobber_option
@quiet_option
def command(captures, output, preset, config_file, model, iters, batch, lr, tex_res, no_visibility,
            light_path, linearity_loss, light_features, no_specular, no_refiner, vgg_weights, resume, device, metrics_out, seed, no_clobber, quiet):
    """Train RelightableHands' teacher on CAPTURE (a relight/capture folder, e.g. from
    synth-capture) and write the checkpoint -o.  With --model linear, several CAPTUREs
    (one per subject) train one universal model (URHand Sec. 4.3, Table 2).

    Per light, texel-aligned maps of the light and view directions in each texel's
    tangent frame and that light's ray-traced visibility go through a U-Net with the
    pose at its bottleneck to a texture and a shadow map (App. A.1, Eq. 10); a frame
    lit by several LEDs is their intensity-weighted sum (Eq. 2), rendered into every
    camera through the fine mesh's G-buffer and compared with the image inside the
    hand mask (Eq. 5: MSE, VGG with --vgg-weights, L_neg).  Trains on the grouped-light
    frames of the training poses; validates on held-out poses, fully lit frames and the
    capture's env-map ground truth.

    --model linear: URHand's model (Sec. 4): a U-Net on the mean texture and pose
    refines normals (displacement) and roughness; GGX shading features of the
    frame's LEDs (Eq. 10-15, visibility, 1/r²) feed a light path with no bias and
    no nonlinearity, modulated by a pose/texture branch (Eq. 5), to a gain and a
    bias over the mean texture (Eq. 6); both renders are L1-supervised (Eq. 7, 9).
    Linear in its features, it renders env maps with no distillation.

    Data-parallel: torchrun --nproc_per_node=N $(which relight) train-teacher ...
    (gloo on CPU, NCCL on CUDA; rank 0 writes).  On a 2-core CPU, two processes of
    one thread (--batch 1 each: the same global batch) ran the cpu preset 1.22x
    faster than one process with two threads.

    \b
    Examples:
      relight train-teacher capture/ -o teacher.pt --preset tiny
      relight train-teacher capture/ -o ggx.pt --model ggx --iters 500
      relight train-teacher capture/ -o teacher.pt --resume teacher_5k.pt --iters 10000
      relight train-teacher capture/ -o linear.pt --model linear
    """
    import os

    from relight_cli.clitools import check_input
    from relight_cli.errors import UsageProblem

    from ._learned import check_outputs, write_validation

    # ---- usage checks before any work
    if iters is not None and iters < 1:
        raise UsageProblem(f"--iters must be ≥ 1, got {iters}")
    if len(captures) > 1 and (model in ("olat", "ggx") or (model is None and resume is None)):
        raise UsageProblem(f"several CAPTUREs (one per subject) train --model linear only, "
                           f"not --model {model or 'olat'}; give one capture")
    folders = []
    for capture in captures:
        if not os.path.isdir(capture):
            from relight_cli.errors import DataError
            if os.path.exists(capture) and os.path.basename(capture) == "capture.json":
                capture = os.path.dirname(capture) or "."
            else:
                raise DataError("CAPTURE must be a capture folder (with capture.json)", capture)
        if os.path.isfile(os.path.join(capture, "capture.json")):
            check_input(os.path.join(capture, "capture.json"))
        same = [f for f in folders if os.path.realpath(f) == os.path.realpath(capture)]
        if same:
            raise UsageProblem(f"CAPTURE {capture} is given twice (also as {same[0]}): give "
                               f"each subject once")
        folders.append(capture)
    capture = folders[0]
    for path, role in ((config_file, "--config"), (vgg_weights, None), (resume, None)):
        if path is not None:
            check_input(path, stdin=role)
    check_outputs(output, metrics_out, no_clobber)

    import torch  # noqa: F401  (after usage checks: --help and usage errors stay fast)

    from relight_cli.errors import DataError
    from relight_cli.formats.checkpoint import read_checkpoint, write_checkpoint
    from relight_cli.neural.config import TeacherConfig, resolve_config, resume_config
    from relight_cli.hand.scene import handedness
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.train import resolve_device, train
    from relight_cli.provenance import outside_transaction, provenance

    overrides = {"model": model, "iters": iters, "batch": batch, "lr": lr, "tex_res": tex_res,
                 "seed": seed, "visibility": False if no_visibility else None}
    linear_only = {"light_path": light_path, "linearity_loss": linearity_loss,
                   "features": light_features, "specular": False if no_specular else None,
                   "refiner": False if no_refiner else None}
    ckpt = read_checkpoint(resume) if resume is not None else None
    kind = ckpt["kind"] if ckpt is not None else ("linear" if model == "linear" else "teacher")
    config_class, resolve, train_model = TeacherConfig, resolve_config, train
    if kind == "linear":
        from relight_cli.neural import linear, linear_train
        overrides.update(linear_only)
        config_class, resolve, train_model = (linear.LinearConfig, linear.resolve_config,
                                              linear_train.train)
    elif kind != "teacher":
        raise DataError(f"checkpoint holds a {kind!r} model, expected a teacher", resume)
    elif len(folders) > 1:
        raise UsageProblem(f"several CAPTUREs (one per subject) train --model linear only; "
                           f"{resume} holds the {ckpt['model']} teacher: give one capture")
    elif any(v is not None for v in linear_only.values()):
        raise UsageProblem("--light-path, --linearity-loss, --features, --no-specular and "
                           "--no-refiner belong to --model linear")
    if ckpt is not None:
        config = resume_config(ckpt, config_class, overrides, config_file, iters, resume)
    else:
        config = resolve(preset, config_file, overrides)
    torch_device = resolve_device(device)

    vgg = None
    if vgg_weights is not None:
        from relight_cli.neural.losses import load_vgg
        vgg = load_vgg(vgg_weights).to(torch_device)
    # ---- data (data errors)
    subjects = [CaptureData(folder, config.tex_res, config.aa, config.visibility,
                            config.falloff, config.holdout, config.cache_poses)
                for folder in folders]
    data = subjects[0]
    if len(subjects) > 1:
        # what one model cannot share (joints, UV layout, hands, sampling), named per capture
        linear_train.check_subjects(subjects)
    if ckpt is not None and len(subjects) == 1 and "subjects" not in ckpt["extra"] \
            and ckpt["capture_key"] != data.key:
        raise DataError(f"checkpoint was trained on another capture (key {ckpt['capture_key']}, "
                        f"this one is {data.key})", resume)
    if ckpt is not None and (len(subjects) > 1 or "subjects" in ckpt["extra"]):
        trained = [r["capture_key"] for r in ckpt["extra"].get("subjects") or
                   [{"capture_key": ckpt["capture_key"]}]]
        if trained != [d.key for d in subjects]:
            raise DataError(f"checkpoint was trained on other subjects (keys "
                            f"{', '.join(trained)}; these captures are "
                            f"{', '.join(d.key for d in subjects)}, in this order)", resume)
    rank = int(os.environ.get("RANK", "0"))
    quiet = quiet or rank != 0
    config.aa = data.aa        # the sampling used, recorded in the checkpoint
    if not data.sampling["matched"]:
        log(f"note: pixels sampled {data.aa}×{data.aa}, but the capture's images were made "
            f"with {data.sampling['capture_aa']}×{data.sampling['capture_aa']} (recorded in "
            f"the scores as sampling.matched = false)", quiet)
    splits = data.splits()
    log(f"read {capture}: {len(splits['train'])} training, {len(splits['heldout'])} held-out, "
        f"{len(splits['fully_lit'])} fully lit, {len(splits.get('env', []))} env-map samples; "
        f"{data.n_hands} hand(s) ({', '.join(handedness(data.hand))}, recorded in the "
        f"checkpoint); model {config.model}, {config.tex_res}² texture, "
        f"{config.iters} iterations on {torch_device}"
        + ("" if vgg is not None else "; no VGG weights: λ_VGG = 0"), quiet)
    for s, other in enumerate(subjects[1:], 1):
        more = other.splits()
        log(f"read {folders[s]} (subject {s}): {len(more['train'])} training, "
            f"{len(more['heldout'])} held-out, {len(more['fully_lit'])} fully lit, "
            f"{len(more.get('env', []))} env-map samples; each subject conditioned on its "
            f"own mean texture (URHand Sec. 4)", quiet)
    if vgg is None:
        config.lambda_vgg = 0.0 if ckpt is None else config.lambda_vgg
    inputs = {"capture": data.index_path}
    for s, other in enumerate(subjects[1:], 1):
        inputs[f"capture.{s}"] = other.index_path
    captures_in = dict(inputs)
    if vgg_weights is not None:
        inputs["vgg_weights"] = vgg_weights
    if resume is not None:
        inputs["resume"] = resume
    if config_file is not None:
        inputs["config"] = config_file
    record = provenance("relight/checkpoint", 1, inputs, {"preset": preset, **config.to_dict()})

    def save(checkpoint):
        # Periodic checkpoints land at once: an interrupted run keeps its progress.
        with outside_transaction():
            write_checkpoint(output, checkpoint)

    result = train_model(data if len(subjects) == 1 else subjects, config, torch_device,
                         resume=ckpt, vgg=vgg, provenance=record,
                   save=save if rank == 0 else None, show_progress=not quiet,
                   log=lambda m: log(m, quiet))
    if rank != 0:
        return
    write_checkpoint(output, result.checkpoint)
    write_validation(metrics_out, result, captures_in, config, record, data.sampling)
    its = result.steps_run / result.seconds if result.seconds > 0 else float("inf")
    from relight_cli.neural.train import _summary
    log(f"wrote {output}: {result.steps_run} step(s) in {result.seconds:.1f} s ({its:.2f} it/s); "
        + _summary(result.history[-1] if result.history else {"step": config.iters}), quiet)
