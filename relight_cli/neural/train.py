"""Training a teacher: Adam on (frame, camera) samples, deterministic, resumable, DDP-capable.

* **Sampling**: step t draws its global batch of ``batch × world`` sample indices from
  ``numpy.random.default_rng([seed, t])``: a pure function of (seed, step), so a resumed
  run draws exactly what the uninterrupted run would, and each DDP rank takes its own
  slice of the same draw.
* **Determinism**: weights are initialized under ``torch.manual_seed(seed)``; CPU runs
  repeat bit for bit (same thread count).  The checkpoint stores the model, Adam's
  state, the step and the torch / numpy / python RNG states, so ``--resume`` after N
  steps reproduces an uninterrupted 2N-step run exactly.  With ``lr_schedule: cosine``
  the rate is a function of (step, iters): resuming a periodic save with the same
  ``--iters`` is exact; extending ``--iters`` stretches the rest of the decay.
* **Scale**: one process, or data-parallel under ``torchrun --nproc_per_node=N`` with
  PyTorch DDP (gloo on CPU, NCCL on CUDA): gradients are averaged over ranks, every rank
  ends with identical weights, only rank 0 writes files and shows progress.
* **Loss** per sample (Eq. 5): λ_MSE·MSE inside the mask + λ_VGG·VGG (if weights were
  given) + λ_neg·γ(t)·L_neg (see :mod:`relight_cli.neural.losses`); the batch loss is the
  mean over samples, back-propagated one sample at a time (memory stays that of one
  frame's lights).
* **Validation** every ``val_every`` steps and at the end: masked MSE, PSNR, SSIM on
  held-out poses, fully lit frames (novel illumination) and the capture's env-map
  ground truth (:func:`evaluate`).
"""

from __future__ import annotations

import collections
import contextlib
import copy
import json
import os
import random
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from relight_cli.envmap import DEFAULT_GRID
from relight_cli.errors import DataError, UsageProblem

from .config import TeacherConfig
from .data import CaptureData
from .losses import masked_mse, neg_weight, negativity
from .models import build_model
from .teacher import env_light_inputs, render_lights, render_sample
from .weights import build_checked, check_weights, load_weights  # noqa: F401


@dataclass
class TrainResult:
    """What a training run produced (the checkpoint dict is written by the caller)."""

    checkpoint: dict
    history: list = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    steps_run: int = 0
    seconds: float = 0.0
    peak_memory_mb: float = 0.0


def resolve_device(name: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is a usage error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise UsageProblem("--device cuda: no CUDA device is available (use auto or cpu)")
    if name not in ("cpu", "cuda"):
        raise UsageProblem(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


def distributed_context(device: torch.device):
    """(rank, world size, local device) — initializing torch.distributed when launched by
    torchrun (WORLD_SIZE > 1): gloo on CPU, NCCL on CUDA."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1, device
    import torch.distributed as dist
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    rank = dist.get_rank()
    if device.type == "cuda":
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        device = torch.device("cuda", local)
    return rank, dist.get_world_size(), device


def batch_indices(seed: int, step: int, n_items: int, count: int) -> np.ndarray:
    """The global batch of step ``step``: ``count`` indices in [0, n_items)."""
    rng = np.random.default_rng([int(seed), int(step)])
    return rng.integers(0, n_items, size=count)


def scheduled_lr(config, step: int) -> float:
    """The learning rate of step ``step`` under ``config.lr_schedule`` (see TeacherConfig)."""
    if getattr(config, "lr_schedule", "constant") != "cosine":
        return config.lr
    import math
    t = min(max(step / max(config.iters, 1), 0.0), 1.0)
    return config.lr_final + 0.5 * (config.lr - config.lr_final) * (1.0 + math.cos(math.pi * t))


def rng_state() -> dict:
    np_state = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]),
                      float(np_state[4])],
            "python": _python_state()}


def _python_state():
    version, internal, gauss = random.getstate()
    return [version, list(internal), gauss]


def set_rng_state(state: dict, source: str | None = None) -> None:
    """Restore the torch / numpy / python RNGs from a checkpoint's ``rng`` field, each
    state checked first (DataError naming ``source``; nothing is restored then)."""
    from relight_cli.formats.checkpoint import decode_rng
    torch_state, np_state, py_state = decode_rng(state, source)
    torch.set_rng_state(torch_state)
    np.random.set_state(np_state)
    random.setstate(py_state)


def sample_loss(model, data: CaptureData, item, config: TeacherConfig, step: int, device,
                vgg=None, mean_texture=None):
    """(total loss, {mse, vgg, neg}) of one (frame, camera) sample (Eq. 5)."""
    sample = data.sample(*item)
    image, raw = render_sample(model, sample, device, mean_texture, return_raw=True)
    target = torch.from_numpy(sample.image).to(device)
    mask = torch.from_numpy((sample.mask > 0) | (sample.gbuffer.mask > 0)).to(device)
    mse = masked_mse(image, target, mask)
    total = config.lambda_mse * mse
    parts = {"mse": float(mse.detach())}
    if vgg is not None and config.lambda_vgg > 0:
        perceptual = vgg(image, target, mask)
        total = total + config.lambda_vgg * perceptual
        parts["vgg"] = float(perceptual.detach())
    if raw is not None and config.lambda_neg > 0:
        gamma = neg_weight(step, config.neg_eta, config.neg_start, config.neg_schedule)
        texels = data.texels(sample.pose)
        region = torch.from_numpy(np.stack([texels.inside(k) for k in sample.hand_of])
                                  [:, None]).to(device)
        neg = negativity(raw, region)
        total = total + config.lambda_neg * gamma * neg
        parts["neg"] = float(neg.detach())
    return total, parts


def _metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    from .scores import score
    return score(pred, gt, mask)


def evaluate(model, data: CaptureData, config: TeacherConfig, device, splits=None,
             mean_texture=None, env_res=DEFAULT_GRID, every: bool = False) -> dict:
    """Per split {mse, psnr, ssim, mae, samples}: means over at most ``val_samples``
    evenly spaced samples (``every``: all of them), masked by the ground-truth hand mask
    (> 0.5)."""
    def frame(item):
        sample = data.sample(*item)
        pred = render_sample(model, sample, device, mean_texture)
        return pred.cpu().numpy(), sample.image, sample.mask

    def env(texels, gbuffer, poses, denv):
        lights, weights = env_light_inputs(texels, denv, config.visibility)
        return render_lights(model, texels, gbuffer, poses, lights, weights, config.visibility,
                             config.falloff, device, mean_texture=mean_texture).cpu().numpy()
    return evaluate_splits(model, data, None if every else config.val_samples, frame, env,
                           splits, env_res)


def evaluate_splits(model, data: CaptureData, val_samples: int, predict_frame, predict_env,
                    splits=None, env_res=DEFAULT_GRID) -> dict:
    """The validation loop of any model: ``predict_frame(item)`` → (prediction, image, mask)
    of a capture (frame, camera) item; ``predict_env(texels, gbuffer, poses, discretized
    env)`` → the prediction of an ``eval/`` env render (held-out hand)."""
    from relight_cli.envmap import discretize_env

    from .scores import attach_ceiling, mean_scores, spread
    model.eval()
    out = {}
    all_splits = data.splits()
    names = splits or [s for s in ("heldout", "fully_lit", "env") if all_splits.get(s)]
    from .ceiling import ceiling_of
    ceiling = ceiling_of(data)
    with torch.no_grad():
        for name in names:
            items = all_splits.get(name) or []
            if not items:
                continue
            pick = spread(len(items), val_samples)
            rows, best = [], []
            for i in pick:
                if name == "env":
                    pose, env_name, camera, gt, mask = data.env_target(items[i][1])
                    texels = data.texels(pose, held_out=True)
                    gb = data.gbuffer(pose, camera, held_out=True)
                    denv = discretize_env(data.env_map(env_name), *env_res)
                    pred = predict_env(texels, gb, data.poses(pose, True), denv)
                else:
                    pred, gt, mask = predict_frame(items[i])
                    frame = data.frame(items[i][0])
                    texels = data.texels(frame.pose)
                    gb = data.gbuffer(frame.pose, data.capture.camera(items[i][1]))
                m = _metrics(pred, gt, mask)
                if m:
                    rows.append(m)
                    if ceiling.available:
                        best.append(ceiling.score(items[i], [texels] * texels.n_hands, gb,
                                                  gt, mask))
            if rows:
                out[name] = attach_ceiling(mean_scores(rows), best)
    model.train()
    return out


def check_training_frames(data: CaptureData, items: list) -> None:
    """Refuse a capture with no training samples, or whose hand does not match its images,
    before any training (DataError naming the file)."""
    if not items:
        raise DataError("no training samples: the training frames list no images",
                        data.index_path)
    data.check_alignment(data.sample(*items[0]))


class TeacherTask:
    """What :func:`fit` needs to train a teacher (``olat`` or ``ggx``) on a capture."""

    kind = "teacher"
    desc = "train-teacher"

    def __init__(self, data: CaptureData, config: TeacherConfig, vgg=None):
        self.data = data
        self.config = config
        self.vgg = vgg
        self.mean_texture = None
        self.items = data.splits()["train"]
        self.model_name = config.model
        self.capture_key = data.key
        self.pose_dim = data.pose_dim

    def check(self):
        check_training_frames(self.data, self.items)

    def build(self, device, resume=None):
        model = build_model(self.config, self.data.pose_dim).to(device)
        if self.config.model == "ggx" and resume is None:    # a resumed run has its own T̄
            mean = self.data.mean_texture().mean(0, keepdims=True)          # [1, 3, N, N]
            self.mean_texture = torch.from_numpy(mean).to(device)
        return model

    def restore(self, resume: dict, device):
        mean = resume.get("extra", {}).get("mean_texture")
        if mean is not None:
            n = self.config.tex_res
            if not isinstance(mean, torch.Tensor) or mean.ndim != 4 or \
                    tuple(mean.shape[1:]) != (3, n, n) or mean.dtype != torch.float32:
                raise ValueError(f"extra.mean_texture must be float32 [1, 3, {n}, {n}]")
            self.mean_texture = mean.to(device)
        elif self.config.model == "ggx":
            raise ValueError("a ggx checkpoint needs its mean texture (extra.mean_texture)")

    def loss(self, net, item, step, device):
        return sample_loss(net, self.data, item, self.config, step, device, self.vgg,
                           self.mean_texture)

    def evaluate(self, model, device, every: bool = False):
        """The validation splits; ``every``: the held-out split, every sample of it."""
        return evaluate(model, self.data, self.config, device, ["heldout"] if every else None,
                        self.mean_texture, every=every)

    def extra(self) -> dict:
        from .geometry import hand_records, uv_layout_digest
        out = {"uv_layout": uv_layout_digest(self.data.hand.mesh("fine")),
               "hands": hand_records(self.data.hand)}
        if self.mean_texture is not None:
            out["mean_texture"] = self.mean_texture.detach().cpu()
        return out


def train(data: CaptureData, config: TeacherConfig, device: torch.device, resume: dict | None = None,
          vgg=None, provenance: dict | None = None, save=None, show_progress: bool = True,
          log=None) -> TrainResult:
    """Train a teacher on ``data`` (see :func:`fit` for the arguments)."""
    return fit(TeacherTask(data, config, vgg), config, device, resume, provenance, save,
               show_progress, log)


def fit(task, config, device: torch.device, resume: dict | None = None,
        provenance: dict | None = None, save=None, show_progress: bool = True,
        log=None) -> TrainResult:
    """The training loop shared by every learned model.

    Args:
        task: the model's data and losses: ``items`` (training items), ``check()``,
            ``build(device, resume)`` → module, ``restore(resume, device)``,
            ``loss(net, item, step, device)`` → (loss, parts), ``evaluate(model, device)``
            → {split: metrics}, ``extra()`` → checkpoint extras; ``kind``, ``model_name``,
            ``capture_key``, ``pose_dim``, ``desc`` (progress label).  Optional:
            ``before_step(optimizer, step)`` (e.g. a learning-rate schedule),
            ``after_step(step, world)`` (e.g. a discriminator's own step), and ``ddp =
            False`` for a model not called through one forward (its gradients are then
            averaged over the ranks by :func:`average_gradients` instead of DDP's hooks).
        config: a configuration with ``iters``, ``batch``, ``lr``, ``seed``, ``val_every``,
            ``save_every`` and ``to_dict()``.
        device: torch device (``resolve_device``).
        resume: a checkpoint dict (``neural.checkpoints.read_checkpoint``) to continue;
            its weights are compared with the module the task builds (on the meta device,
            before allocating it) and its whole state with this run's model and
            optimizer (:func:`restore_state`) before any of it is used.
        provenance: stored in the checkpoint.
        save: callable(checkpoint dict) for periodic saves (rank 0; ``save_every``); each
            dict is a snapshot (its tensors are copies), so a caller may keep it.
        show_progress: progress on stderr (rank 0): a tqdm bar on a terminal, else plain lines.
        log: callable(str) for log lines.

    Returns:
        :class:`TrainResult` (its checkpoint is the final state).
    """
    from relight_cli.formats.checkpoint import make_checkpoint

    rank, world, device = distributed_context(device)
    task.check()
    items = task.items
    torch.manual_seed(config.seed)
    np.random.seed(config.seed % (2 ** 32))
    random.seed(config.seed)
    if resume is not None:
        # the checkpoint's weights must be those of the module its configuration builds,
        # compared on the meta device before anything is allocated for it
        check_resume_weights(lambda: task.build(torch.device("meta"), resume), resume)
    model = task.build(device, resume)
    if getattr(config, "channels_last", False):
        model = model.to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
    start = 0
    averaged = None
    if float(getattr(config, "ema", 0.0) or 0.0) > 0:
        averaged = averaged_model(model, config.ema)
    if resume is not None:
        start = restore_state(task, model, optimizer, resume, device, averaged)
    # what validations score and the checkpoint holds: the weights' average when kept
    scored = model if averaged is None else averaged.module
    net = model
    use_ddp = world > 1 and getattr(task, "ddp", True)
    before_step = getattr(task, "before_step", None)
    after_step = getattr(task, "after_step", None)
    if use_ddp:
        from torch.nn.parallel import DistributedDataParallel
        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda"
                                      else None)
    bar = None
    if show_progress and rank == 0:
        from relight_cli.progress import progress
        bar = progress(total=config.iters, initial=start, desc=task.desc, unit="it")
    history = []
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t_start = time.perf_counter()
    model.train()

    def weights(module):
        return {k: v.detach().cpu().contiguous().clone() for k, v in module.state_dict().items()}

    def checkpoint(step):
        extra = copy.deepcopy(task.extra())
        if averaged is not None:
            extra["training_weights"] = weights(model)
        return make_checkpoint(task.kind, task.model_name, config.to_dict(), step,
                               weights(scored), copy.deepcopy(optimizer.state_dict()),
                               rng_state(), task.capture_key,
                               task.pose_dim, provenance or {}, extra)

    cosine = getattr(config, "lr_schedule", "constant") == "cosine"
    # of the last COLLAPSE_WINDOW steps, those whose every gradient was exactly zero
    still = collections.deque(maxlen=COLLAPSE_WINDOW)
    for step in range(start, config.iters):
        if cosine:
            for group in optimizer.param_groups:
                group["lr"] = scheduled_lr(config, step)
        if before_step is not None:
            before_step(optimizer, step)
        indices = batch_indices(config.seed, step, len(items), config.batch * world)
        mine = indices[rank * config.batch:(rank + 1) * config.batch]
        optimizer.zero_grad(set_to_none=True)
        parts_sum = {}
        for j, index in enumerate(mine):
            sync = (j == len(mine) - 1) or not use_ddp
            ctx = contextlib.nullcontext() if sync else net.no_sync()
            with ctx:
                loss, parts = task.loss(net, items[int(index)], step, device)
                (loss / len(mine)).backward()
            for k, v in parts.items():
                parts_sum[k] = parts_sum.get(k, 0.0) + v / len(mine)
        if world > 1 and not use_ddp:
            average_gradients(model, world)
        try:
            vanished = check_gradients(model, step, config.iters, parts_sum, task)  # all ranks
        except TrainingDiverged:
            _close_group(world)      # every rank raises it at this step: they close together
            raise
        if vanished:                # ... and counted only where some rank's loss is not 0
            vanished = any_rank(any(v > 0 for v in parts_sum.values()), world, device)
        still.append(vanished)
        if sum(still) >= COLLAPSE_STEPS:
            # every rank counts the same steps: close the group together, or the rank that
            # exits first leaves the other's gloo pair to abort the job (SIGABRT)
            _close_group(world)
            raise TrainingCollapsed(step, config.iters, parts_sum, task)
        optimizer.step()
        if averaged is not None:
            averaged.update_parameters(model)
        if after_step is not None:
            after_step(step, world)
        done = step + 1
        if bar is not None:
            bar.set_postfix({k: f"{v:.3g}" for k, v in parts_sum.items()}, refresh=False)
            bar.update(1)
        if config.val_every and done % config.val_every == 0 and done < config.iters and rank == 0:
            record = {"step": done, **task.evaluate(scored, device)}
            history.append(record)
            if log:
                log(_summary(record))
        if save is not None and rank == 0 and config.save_every and done % config.save_every == 0 \
                and done < config.iters:
            save(checkpoint(done))
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t_start
    final = {}
    if rank == 0:
        if log:     # it can take minutes on a large capture: say what the silence is
            log("final validation: scoring the model on the capture's validation samples, "
                "each beside its ceiling")
        final = {"step": config.iters, **task.evaluate(scored, device)}
        history.append(final)
        every = evaluate_every(task, scored, device)
        if every is not None:          # in the final metrics only: the curve stays on
            final = {**final, "heldout_all": every}     # the same samples throughout
    peak = (torch.cuda.max_memory_allocated(device) / 2 ** 20 if device.type == "cuda" else
            _peak_rss_mb())
    result = TrainResult(checkpoint(config.iters), history, final, config.iters - start, seconds,
                         peak)
    # every rank waits for rank 0's final validation, then the group closes cleanly
    _close_group(world)
    return result


def _close_group(world: int) -> None:
    """Every rank waits at a barrier, then the process group closes (a rank leaving while
    another still talks through gloo aborts the whole job).  A no-op in one process."""
    if world <= 1:
        return
    import torch.distributed as dist
    if dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


class TrainingDiverged(DataError):
    """A training step produced a non-finite gradient: the run stops before the optimizer
    takes it, so no weight, moment or checkpoint ever holds NaN/Inf.  Exit 1."""


#: a run is called collapsed when every gradient was exactly zero in COLLAPSE_STEPS of its
#: last COLLAPSE_WINDOW steps while its loss was not (a healthy model never has such a
#: step; the dead teacher below had them in 58 % of its batches — 23 of 40 sampled — and
#: gradients ≤ 1.3e-6 in the rest, a few texels still lit)
COLLAPSE_STEPS, COLLAPSE_WINDOW = 25, 100


class TrainingCollapsed(TrainingDiverged):
    """Every gradient was exactly zero in :data:`COLLAPSE_STEPS` of the last
    :data:`COLLAPSE_WINDOW` steps: the model's output saturated where no gradient reaches
    it, and it cannot recover.  Seen:
    an OLAT teacher at the ``cpu`` preset's lr 2e-3 stretched to 12,000 iterations (the
    converged capture, seed 0) whose shadow gate closed everywhere between steps 3,300
    and 3,600 (S down to −2·10⁴, σ(S) underflowing to 0, a black render: loss 4e-3,
    every gradient 0.0 — finite, so :func:`check_gradients` cannot see it).  Exit 1;
    studies record it as a diverged row (a subclass of :class:`TrainingDiverged`)."""

    def __init__(self, step: int, iters: int, parts: dict, task):
        losses = ", ".join(f"{k} {v:.4g}" for k, v in parts.items())
        data = getattr(task, "data", None)
        super().__init__(
            f"training collapsed at step {step + 1} of {iters}: every gradient was exactly "
            f"zero in {COLLAPSE_STEPS} of the last {COLLAPSE_WINDOW} steps (this batch: "
            f"{losses or 'loss unknown'}), so "
            f"the model's output has saturated (e.g. an OLAT teacher's shadow gate closed "
            f"everywhere) and cannot recover; train again with a lower --lr",
            getattr(data, "index_path", None))


def evaluate_every(task, model, device):
    """The final checkpoint's held-out split scored on *every* sample (with its ceiling),
    or None (a task that cannot, or a capture without held-out frames).  Validation
    scores ``val_samples`` evenly spaced samples, which can misstate the gap: an OLAT
    teacher of the converged study read 3.8 dB below its ceiling on 16 held-out samples
    and 2.05 dB on all 128 (benchmarks/results/converged/teacher_inputs.md)."""
    import inspect
    if "every" not in inspect.signature(task.evaluate).parameters:
        return None
    return task.evaluate(model, device, every=True).get("heldout")


def any_rank(flag: bool, world: int, device) -> bool:
    """``flag`` or-ed over the ranks (a collective: every rank must call it)."""
    if world <= 1:
        return bool(flag)
    import torch.distributed as dist
    t = torch.tensor([int(bool(flag))], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def check_gradients(model, step: int, iters: int, parts: dict, task) -> bool:
    """TrainingDiverged when any gradient of ``model`` is NaN/Inf; else whether every
    gradient is exactly zero (a collapsed step, :class:`TrainingCollapsed`).  One pass:
    the largest |g| of each parameter (NaN and Inf propagate through it).  Called after
    the ranks' gradients are averaged, so every rank sees the same answer and stops
    together."""
    grads = [(name, p.grad) for name, p in model.named_parameters() if p.grad is not None]
    if not grads:
        return False
    largest = torch.stack([g.detach().abs().amax() for _, g in grads])
    if bool(torch.isfinite(largest).all()):
        return not bool((largest > 0).any())
    name = next(n for (n, _), m in zip(grads, largest) if not bool(torch.isfinite(m)))
    losses = ", ".join(f"{k} {v:.4g}" for k, v in parts.items())
    data = getattr(task, "data", None)
    raise TrainingDiverged(
        f"training diverged at step {step + 1} of {iters}: non-finite gradient of {name} "
        f"(batch {losses or 'loss unknown'}); nothing was updated",
        getattr(data, "index_path", None))


def average_gradients(model, world: int) -> None:
    """All-reduce (mean) every gradient over the ranks in one flat call: for models called
    through several branches rather than one forward, whose gradients DDP's hooks would
    not see."""
    import torch.distributed as dist
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in model.parameters()]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world
    offset = 0
    for p, g in zip(model.parameters(), grads):
        n = g.numel()
        p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n


def _peak_rss_mb() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _summary(record: dict) -> str:
    parts = [f"step {record['step']}"]
    for split, m in record.items():
        if isinstance(m, dict) and "psnr" in m:
            parts.append(f"{split}: MSE {m['mse'] * 1e3:.3f}e-3 PSNR {m['psnr']:.2f} dB "
                         f"SSIM {m['ssim']:.3f}")
    return "; ".join(parts)


def check_resume_weights(build_meta, resume: dict) -> None:
    """A resumed checkpoint's weights against the module its task builds (on the meta
    device); DataError naming the checkpoint."""
    with torch.device("meta"):
        probe = build_meta()
    try:
        check_weights(probe.state_dict(), resume["weights"])
    except ValueError as exc:
        raise DataError(str(exc), resume.get("path")) from None


def check_optimizer_state(optimizer, state, what: str = "optimizer") -> None:
    """A saved Adam ``state_dict()`` against ``optimizer`` (built over the model's
    parameters): the same groups over the same parameter indices, the same
    hyperparameters but the learning rate (a schedule's to set), and each parameter's
    moments of its shape and dtype, finite, the second moment ≥ 0.  ValueError naming
    the first difference; the optimizer is untouched."""
    import math
    fresh = optimizer.state_dict()
    if not isinstance(state, dict) or not isinstance(state.get("param_groups"), list) \
            or not isinstance(state.get("state"), dict):
        raise ValueError(f"{what} must be an optimizer state dict (state, param_groups)")
    if len(state["param_groups"]) != len(fresh["param_groups"]):
        raise ValueError(f"{what} has {len(state['param_groups'])} parameter group(s), the "
                         f"model's has {len(fresh['param_groups'])}")
    params = {}
    for saved, group, live in zip(state["param_groups"], fresh["param_groups"],
                                  optimizer.param_groups):
        if not isinstance(saved, dict) or saved.get("params") != group["params"]:
            raise ValueError(f"{what} groups list other parameters than the model's "
                             f"({len(group['params'])} in a group)")
        extra = sorted(str(k) for k in set(saved) - set(group))
        if extra:
            raise ValueError(f"{what} has unknown hyperparameter {extra[0][:40]}")
        for key, value in saved.items():
            if key == "params":
                continue
            if key == "lr":
                if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                        not math.isfinite(value) or not 0 < value <= 10:
                    raise ValueError(f"{what} learning rate must be in (0, 10], got "
                                     f"{value!r}"[:120])
            elif type(value) is not type(group[key]) or value != group[key]:
                raise ValueError(f"{what} hyperparameter {key} is {value!r}, this model's "
                                 f"optimizer has {group[key]!r}"[:160])
        for i, p in zip(group["params"], live["params"]):
            params[i] = p
    amsgrad = any(g.get("amsgrad") for g in fresh["param_groups"])
    keys = {"step", "exp_avg", "exp_avg_sq"} | ({"max_exp_avg_sq"} if amsgrad else set())
    for i, entry in state["state"].items():
        if i not in params:
            raise ValueError(f"{what} has moments for parameter {i!r}, which the model does "
                             f"not have"[:160])
        if not isinstance(entry, dict) or set(entry) != keys:
            raise ValueError(f"{what} state of parameter {i} must hold {', '.join(sorted(keys))}")
        step = entry["step"]
        if isinstance(step, torch.Tensor):
            if step.ndim != 0 or not step.is_floating_point():
                raise ValueError(f"{what} step of parameter {i} must be a scalar")
            step = float(step)
        if isinstance(step, bool) or not isinstance(step, (int, float)) or \
                not math.isfinite(step) or not 0 <= step <= 1e9 or step != int(step):
            raise ValueError(f"{what} step of parameter {i} must be a count, got {step!r}"[:120])
        p = params[i]
        for key in keys - {"step"}:
            moment = entry[key]
            if not isinstance(moment, torch.Tensor) or tuple(moment.shape) != tuple(p.shape) \
                    or moment.dtype != p.dtype:
                got = (tuple(moment.shape), moment.dtype) if isinstance(moment, torch.Tensor) \
                    else type(moment).__name__
                raise ValueError(f"{what} {key} of parameter {i} must be {p.dtype} "
                                 f"{tuple(p.shape)}, got {got}"[:160])
            if not bool(torch.isfinite(moment).all()) or (key != "exp_avg" and
                                                          bool((moment < 0).any())):
                raise ValueError(f"{what} {key} of parameter {i} holds NaN/Inf or negative "
                                 f"values")


def averaged_model(model, decay: float):
    """An exponential moving average of ``model``'s weights and buffers (Polyak
    averaging; torch's :class:`~torch.optim.swa_utils.AveragedModel`): w̄ ← d·w̄ + (1 − d)·w
    after every optimizer step, w̄ = w at the first."""
    from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
    return AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(decay), use_buffers=True)


def restore_state(task, model, optimizer, resume: dict, device, averaged=None) -> int:
    """Continue from a read checkpoint: its weights, Adam state, step, RNG states and the
    task's own extras (``task.restore``; a task's second module and optimizer, ``disc`` and
    ``opt_d``, from ``extra.discriminator`` / ``extra.optimizer_discriminator``), all
    checked against this run's modules and optimizers before any is used.  With
    ``averaged`` (:func:`averaged_model`) the checkpoint's weights are the average and
    ``extra.training_weights`` the raw ones.  Returns the step to continue from.
    DataError naming the checkpoint (``resume["path"]``) for anything that does not fit."""
    from relight_cli.formats.checkpoint import decode_rng
    source = resume.get("path")
    try:
        check_weights(model.state_dict(), resume["weights"])
        check_optimizer_state(optimizer, resume["optimizer"])
        step = resume["step"]
        if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= 10 ** 9:
            raise ValueError(f"checkpoint step must be an integer count, got {step!r}"[:120])
        extra = resume.get("extra", {})
        if not isinstance(extra, dict):
            raise ValueError("checkpoint extra must be a dict")
        disc, opt_d = getattr(task, "disc", None), getattr(task, "opt_d", None)
        if disc is not None:
            check_weights(disc.state_dict(), extra.get("discriminator"),
                          "checkpoint extra.discriminator")
            check_optimizer_state(opt_d, extra.get("optimizer_discriminator"),
                                  "extra.optimizer_discriminator")
        raw = resume["weights"]
        if averaged is not None:
            if "training_weights" not in extra:
                raise ValueError("it has no extra.training_weights: it was not trained with "
                                 "ema, so its averaged weights cannot be continued")
            raw = extra["training_weights"]
            check_weights(model.state_dict(), raw, "checkpoint extra.training_weights")
        decode_rng(resume["rng"], source)
        model.load_state_dict(raw)
        if averaged is not None:
            averaged.module.load_state_dict(resume["weights"])
            averaged.n_averaged.fill_(max(int(step), 1))
        optimizer.load_state_dict(resume["optimizer"])
        task.restore(resume, device)
    except DataError:
        raise
    except (ValueError, KeyError, TypeError, RuntimeError) as exc:
        # task.restore's own loads fail inside torch: still one line naming the checkpoint
        text = (str(exc).splitlines() or [type(exc).__name__])[0][:160]
        raise DataError(f"cannot resume from this checkpoint: {text}", source) from None
    set_rng_state(resume["rng"], source)
    return step


