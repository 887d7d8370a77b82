"""``relight train-teacher``: RelightableHands' OLAT teacher (or its GGX baseline), or URHand's
linear model, from a capture."""

from __future__ import annotations

import click

from relight_cli.cli.tools import SquareSize, log, no_clobber_option, quiet_option
from relight_cli.neural.registry import architectures, for_architecture, names

from ._learned import training_options


@click.command("train-teacher",
               short_help="Train the OLAT teacher, its GGX baseline or URHand's linear model "
                          "on a capture.")
@click.argument("captures", metavar="CAPTURE...", nargs=-1, required=True)
@click.option("-o", "--output", required=True, metavar="TEACHER.pt",
              help="Checkpoint to write (relight/checkpoint, formats/checkpoint.md).")
@click.option("--preset", type=click.Choice(["tiny", "cpu", "paper"]), default="tiny",
              show_default=True,
              help="tiny: 32² texture, ~150 iterations, minutes, far from converged (tests, "
                   "demo; on the demo capture 141 s for the olat teacher and 286 s for "
                   "linear, on 2 shared CPU cores, final validation included); "
                   "cpu: 64² texture, 6000 iterations with a cosine learning-rate decay "
                   "from 2e-3 (5e-4 for ggx, which collapses at 2e-3), the olat teacher "
                   "with the student's shading features as further input (inputs: "
                   "shading; --config '{\"inputs\": \"paper\"}' for App. A.1's), "
                   "about 10-30 min on 2 CPU cores (benchmarks/results/converged/ says how "
                   "close each model comes to its ceiling); paper: the papers' sizes and "
                   "iterations (100k teacher, 2M linear model: a GPU job).")
@click.option("--config", "config_file", default=None, metavar="FILE.json",
              help="JSON object of config fields overriding the preset (see "
                   "formats/checkpoint.md; '-': stdin).")
@click.option("--model", type=click.Choice(architectures(trainer="train-teacher")), default=None,
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

    from . import _learned as L

    # ---- options (usage errors, before any work)
    folders = _check_usage(captures, output, model, iters, config_file, vgg_weights, resume,
                           metrics_out, no_clobber)

    import torch  # noqa: F401  (after usage checks: --help and usage errors stay fast)

    from relight_cli.formats.checkpoint import write_checkpoint
    from relight_cli.jobs import train_teacher as job
    from relight_cli.provenance import provenance

    # ---- inputs (data errors), the job, the outputs (rank 0 writes)
    rank = int(os.environ.get("RANK", "0"))
    quiet = quiet or rank != 0
    options = _job_options(model, preset, config_file, resume, device, vgg_weights, len(folders),
                           not quiet, {
        "iters": iters, "batch": batch, "lr": lr, "tex_res": tex_res, "seed": seed,
        "visibility": False if no_visibility else None}, {
        "light_path": light_path, "linearity_loss": linearity_loss, "features": light_features,
        "specular": False if no_specular else None, "refiner": False if no_refiner else None})
    subjects = L.read_captures(folders, options.config)
    captures_in = {"capture": subjects[0].index_path,
                   **{f"capture.{s}": d.index_path for s, d in enumerate(subjects[1:], 1)}}
    inputs = {**captures_in, **L.file_inputs(vgg_weights, resume, config_file)}
    trained = job.run(subjects, options,
                      provenance=lambda settings: provenance("relight/checkpoint", 1, inputs,
                                                             settings),
                      save=L.saver(output) if rank == 0 else None,
                      log=lambda m: log(m, quiet), names=folders)
    if rank != 0:
        return
    write_checkpoint(output, trained.result.checkpoint)
    L.write_validation(metrics_out, trained.result, captures_in, trained.config, trained.record,
                       trained.sampling)
    log(f"wrote {output}: {job.summary(trained.result)}", quiet)


def _check_usage(captures, output, model, iters, config_file, vgg_weights, resume, metrics_out,
                 no_clobber) -> list:
    """The options' usage errors (exit 2), before any work: the CAPTURE folders."""
    import os

    from relight_cli.errors import UsageProblem

    from . import _learned as L

    if iters is not None and iters < 1:
        raise UsageProblem(f"--iters must be ≥ 1, got {iters}")
    default = architectures(trainer="train-teacher")[0]
    if len(captures) > 1 and resume is None and not for_architecture(model or default).subjects:
        raise UsageProblem(f"several CAPTUREs (one per subject) train --model "
                           f"{' or '.join(names(subjects=True))} only, not --model "
                           f"{model or default}; give one capture")
    folders = []
    for capture in captures:
        capture = L.check_capture(capture)
        same = [f for f in folders if os.path.realpath(f) == os.path.realpath(capture)]
        if same:
            raise UsageProblem(f"CAPTURE {capture} is given twice (also as {same[0]}): give "
                               f"each subject once")
        folders.append(capture)
    L.check_inputs(config_file, vgg_weights, resume)
    L.check_outputs(output, metrics_out, no_clobber)
    return folders


def _job_options(model, preset, config_file, resume, device, vgg_weights, n_subjects: int,
                 progress: bool, overrides: dict, only: dict):
    """The job's Options, from the inputs (data errors): the --resume checkpoint, the
    configuration (preset, --config, the flags' ``overrides`` and the model's ``only``
    flags), the device and the VGG loss."""
    from relight_cli.jobs import train_teacher as job
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural.train import resolve_device

    from . import _learned as L

    ckpt = read_checkpoint(resume) if resume is not None else None
    config = job.configure(model, preset, config_file, overrides, only, ckpt, resume, n_subjects)
    torch_device = resolve_device(device)
    return job.Options(config, preset, torch_device, L.read_vgg(vgg_weights, torch_device), ckpt,
                       resume, progress=progress)
