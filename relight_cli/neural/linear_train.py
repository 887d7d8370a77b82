"""Training and rendering URHand's linear model (Sec. 4.3): grouped-light frames only.

* **Subjects** (URHand Sec. 4, Fig. 2; Table 2's "trained subject" / "unseen subject"
  columns): one universal model trained on one capture per subject at once, each
  sample conditioned on its own subject's T̄ (:class:`LinearTask` takes a list of
  CaptureData; :func:`check_subjects` says what they must share).  The checkpoint
  records them (``extra.subjects``, ``extra.mean_textures``); an unseen subject is
  scored with its own capture's T̄ (:mod:`relight_cli.neural.evaluate`).
* **Inputs**: the subject's T̄ (:func:`albedo_texture`), per sample the frame's LEDs as
  point lights (positions, RGB intensities, 1/r², visibility traced once per pose and
  LED group by :class:`~relight_cli.neural.data.CaptureData`) and the camera's view.
  One pass of the model per sample, whatever the number of lights: features are sums.
* **Loss** (Eq. 7): λ_img L1(C) + λ_pb L1(C_pb) (both renders supervised, Sec. 4.3)
  + λ_VGG perceptual (local weights only) + λ_reg Σ_j mean |F_l-enc^j| (Eq. 9 on the
  encoder's maps at the features' unit scale, λ_reg converted from the paper's 8-bit units:
  :func:`reg_weight`; ``reg_layers="all"`` adds the decoder's maps) + λ_lc L_lc (Eq. 17,
  ablation: the frame's LEDs split in two halves, random a₁, a₂ ∈ (0, 1), RMS)
  + λ_GAN L_G (Eq. 8, :mod:`relight_cli.neural.adversarial`; its discriminator takes one
  Adam step (β 0.5, 0.999) per step on the batch's real and rendered images, and its
  weights and Adam state live in the checkpoint's ``extra``).
* **Sampling, determinism, resume, DDP, validation**: those of
  :mod:`relight_cli.neural.train` (batches from (seed, step), RNG states stored; rank 0
  writes; held-out poses, fully lit frames, env-map ground truth).  Under torchrun the
  gradients are averaged by one all-reduce per step: the model is called through its
  branches, not one forward, so DDP's hooks would not see them.  The learning rate drops from ``lr`` to ``lr_final``
  at iteration ``lr_drop`` (a function of the step: resume stays exact).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from .config import PAPER_UNIT
from .linear import LinearConfig, URHandModel, render_textures
from .train import (TrainResult, average_gradients, check_training_frames, evaluate_splits,
                    fit)


def albedo_texture(data, max_frames: int = 4, max_views: int = 64) -> np.ndarray:
    """T̄ [1, 3, N, N] float32 in sr⁻¹: the capture's visibility-aware mean texture
    (:meth:`CaptureData.mean_texture`, radiance) over the fully lit irradiance E of each
    texel (its diffuse feature Eq. 10 under every LED, coarse normal, averaged over up to
    ``max_frames`` fully lit frames), E clamped to ≥ ¼ of its median so texels deep in a
    crevice do not blow up.  A white Lambertian texel gets 1/π.  Hands are averaged
    (one identity)."""
    mean = data.mean_texture(max_views).astype(np.float64)               # [H, 3, N, N]
    frames = (data.fully_lit_frames or data.train_frames)[:max_frames]
    n = data.tex_res
    irradiance = np.zeros((data.n_hands, n, n))
    for frame in frames:
        texels = data.texels(frame.pose)
        lights = data.light_inputs(frame.pose, frame.lights_on)
        power = data.capture.light_intensity[np.asarray(frame.lights_on, np.int64)].mean(1)
        for k in range(data.n_hands):
            cos = np.clip(lights[k].local_light[..., 2], 0, None)
            e = (power[:, None] * lights[k].falloff * lights[k].visibility * cos).sum(0)
            irradiance[k] += texels.to_maps(k, e[:, None].astype(np.float64))[0]
    irradiance /= max(len(frames), 1)
    out = np.zeros_like(mean)
    for k in range(data.n_hands):
        inside = data.texels(frames[0].pose).inside(k)
        e = irradiance[k]
        floor = 0.25 * np.median(e[inside]) if inside.any() else 1.0
        out[k] = mean[k] / np.maximum(e, max(floor, 1e-12))[None]
    return out.mean(0, keepdims=True).astype(np.float32)


def feature_scale(data, n_frames: int = 4) -> float:
    """Mean diffuse irradiance over the inside texels of the first training frames: the
    fixed scale features enter the light path at (the model stays the same linear map)."""
    values = []
    for frame in data.train_frames[:n_frames]:
        lights = data.light_inputs(frame.pose, frame.lights_on)
        power = data.capture.light_intensity[np.asarray(frame.lights_on, np.int64)].mean(1)
        for li in lights:
            cos = np.clip(li.local_light[..., 2], 0, None)
            values.append(float((power[:, None] * li.falloff * li.visibility * cos).sum(0).mean()))
    scale = float(np.mean(values)) if values else 1.0
    return scale if scale > 0 and np.isfinite(scale) else 1.0


def subjects_feature_scale(datas: list) -> float:
    """The one feature scale of a model trained on several subjects: the mean of each
    subject's :func:`feature_scale` (every subject weighs the same).  It stays one number
    (the model's ``feature_scale`` buffer), not one per subject: it normalises the stage's
    lighting (LED power, distances, visibility), not the identity, which enters through
    T̄ alone (URHand Sec. 4.2: the light path takes the shading features, the identity
    the non-linear branch); an unseen subject at test time is scored through the same
    stored scale.  For one subject it is exactly :func:`feature_scale`."""
    scales = [feature_scale(d) for d in datas]
    scale = float(np.mean(scales)) if scales else 1.0
    return scale if scale > 0 and np.isfinite(scale) else 1.0


def skin_seed(data):
    """The capture's ``settings.skin_seed`` (synth-capture's subject, formats/capture.md)
    as an int, else None (a real capture, or one that does not say)."""
    settings = getattr(data.capture, "settings", None) or {}
    value = settings.get("skin_seed") if isinstance(settings, dict) else None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def subject_records(datas: list) -> list:
    """``extra.subjects`` of a model trained on ``datas`` (one capture per subject, URHand
    Sec. 4.3): per subject {"capture_key", "skin_seed" (int or None), "mean_texture": its
    row of ``extra.mean_textures``}."""
    return [{"capture_key": str(d.key), "skin_seed": skin_seed(d), "mean_texture": i}
            for i, d in enumerate(datas)]


def check_subjects(datas: list) -> None:
    """Refuse subjects that cannot share one model (DataError naming the odd capture's
    file): every capture must have the first one's hand joints (the pose vector), its
    fine mesh's UV layout (the texel-aligned maps), its hands (count, handedness, UV
    charts: the checkpoint records one set) and its pixel sampling (``config.aa``: one
    value recorded); a capture may not be given twice (its key).  Light and camera
    counts, poses and frames may differ (URHand Sec. 4: one stage, many identities)."""
    from relight_cli.errors import DataError

    from .geometry import hand_records, uv_layout_digest
    if len(datas) < 2:
        return
    first = datas[0]
    layout = uv_layout_digest(first.hand.mesh("fine"))
    hands = hand_records(first.hand)
    seen = {first.key: first.index_path}
    for d in datas[1:]:
        if d.hand.n_joints != first.hand.n_joints:
            raise DataError(f"this capture's hand has {d.hand.n_joints} joints, the first "
                            f"capture's {first.hand.n_joints} ({first.index_path}): one model "
                            f"takes one pose vector", d.hand_path)
        if uv_layout_digest(d.hand.mesh("fine")) != layout:
            raise DataError(f"this capture's hand has another UV layout than the first "
                            f"capture's ({first.index_path}): one model learns one texel "
                            f"layout", d.hand_path)
        theirs = hand_records(d.hand)
        if theirs != hands:
            sides = lambda r: "/".join(h["side"] for h in r)              # noqa: E731
            raise DataError(f"this capture's hands ({sides(theirs)}) are not the first "
                            f"capture's ({sides(hands)}, {first.index_path}): the checkpoint "
                            f"records one set of hands", d.hand_path)
        if d.aa != first.aa:
            raise DataError(f"this capture's pixels are sampled {d.aa}×{d.aa}, the first "
                            f"capture's {first.aa}×{first.aa} ({first.index_path}): one "
                            f"model trains through one sampling (config.aa)", d.index_path)
        if d.key in seen:
            raise DataError(f"this capture is the same subject capture as {seen[d.key]} "
                            f"(key {d.key}): give each subject once", d.index_path)
        seen[d.key] = d.index_path


def reg_weight(config: LinearConfig, scale) -> float:
    """Eq. 9's weight in our units: λ_reg · PAPER_UNIT · feature_scale.

    Eq. 7 adds λ_reg L_reg to an image L1 measured in the paper's 8-bit pixel units (255 =
    white; the authors' code: images and T̄ in 0–255, L1 a mean over pixels).  Its light
    path sees O(1) features (the authors divide the shading features by the lights' total
    intensity and multiply the output back), as ours does (features ÷ ``feature_scale`` s),
    so L_reg means the same number in both.  Our L1 is radiance: the network's output o
    gives C = s (o_g T̄ + o_b σ_T), T̄ = PAPER_UNIT · T̄_paper, so one paper pixel unit at the
    normalised maps' scale is PAPER_UNIT · s of our radiance, and matching the paper's
    balance of the two terms needs λ = λ_reg · PAPER_UNIT · s (0.01 → 1.25e-5 · s).
    The paper's 0.01 used directly on our radiance loss is 1 / (PAPER_UNIT · s) ≈ 1.5–3 ×
    10³ times too strong (s ≈ 0.3–0.55 on our synthetic captures); with the decoder's maps
    penalized too it trained the learned light path to zero.
    """
    return float(config.lambda_reg) * PAPER_UNIT * float(scale)


def light_path_l1(intermediate: dict, layers: str = "encoder") -> torch.Tensor:
    """L_reg of Eq. 9 for one hand: Σ_j mean |F^j| over the light path's encoder maps
    F_l-enc^j (``layers="encoder"``, the paper's Eq. 9 and the authors' code) or over its
    encoder and decoder maps (``"all"``); maps from :meth:`LightPath.forward`."""
    maps = list(intermediate["encoder"])
    if layers == "all":
        maps += list(intermediate["decoder"])
    return sum(f.abs().mean() for f in maps)


def learned_share(neural: torch.Tensor, physical: torch.Tensor, image, mask) -> tuple:
    """(Σ|C − C_pb|², Σ|I|²) over the hand's pixels: the learned light path's part of a
    render (neural render minus the physical branch's) against the image; the share is
    √(first / second) summed over samples."""
    m = torch.as_tensor(np.asarray(mask) > 0, device=neural.device)
    img = torch.as_tensor(np.asarray(image), device=neural.device, dtype=neural.dtype)
    return (float(((neural - physical)[m] ** 2).sum()), float((img[m] ** 2).sum()))


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean |pred − target| over mask pixels; [H, W, 3], mask [H, W] bool."""
    m = mask.to(pred.dtype)[..., None]
    return ((pred - target).abs() * m).sum() / torch.clamp(m.sum() * pred.shape[-1], min=1.0)


def lights_of(data, frame_index: int, held_out: bool = False):
    """(per-hand LightInputs, [L, 3] intensities) of a capture frame's LEDs."""
    frame = data.frame(frame_index)
    lights = data.light_inputs(frame.pose, frame.lights_on, held_out)
    return lights, data.capture.light_intensity[np.asarray(frame.lights_on, np.int64)]


def render_image(model, texels, gbuffer, poses, light_inputs, intensity, mean_texture,
                 physical: bool = False, background=0.0):
    """(image [H, W, 3], physical image or None, Textures) of a posed scene under lights."""
    from .teacher import composite
    views = [texels.local_view(k, gbuffer.eye) for k in range(texels.n_hands)]
    tex = render_textures(model, texels, views, light_inputs, intensity, poses, mean_texture,
                          physical)
    image = composite(tex.neural, gbuffer, background)
    pb = composite(tex.physical, gbuffer, background) if physical else None
    return image, pb, tex


def sample_loss(model, data, item, config: LinearConfig, step: int, device, mean_texture,
                vgg=None, disc=None):
    """(total loss, {l1, l1_pb, vgg, reg, lc, gan}, discriminator inputs or None) of one
    (frame, camera) sample (Eq. 7)."""
    sample = data.sample(*item)
    texels = data.texels(sample.pose)
    lights, intensity = lights_of(data, sample.frame)
    image, pb, tex = render_image(model, texels, sample.gbuffer, sample.poses, lights, intensity,
                                  mean_texture, physical=config.lambda_pb > 0)
    target = torch.from_numpy(sample.image).to(device)
    mask = torch.from_numpy((sample.mask > 0) | (sample.gbuffer.mask > 0)).to(device)
    l1 = masked_l1(image, target, mask)
    total = config.lambda_img * l1
    parts = {"l1": float(l1.detach())}
    if pb is not None:
        l1_pb = masked_l1(pb, target, mask)
        total = total + config.lambda_pb * l1_pb
        parts["l1_pb"] = float(l1_pb.detach())
    if vgg is not None and config.lambda_vgg > 0:
        perceptual = vgg(image, target, mask)
        total = total + config.lambda_vgg * perceptual
        parts["vgg"] = float(perceptual.detach())
    if config.lambda_reg > 0:
        reg = sum(light_path_l1(inter, config.reg_layers) for inter in tex.intermediate)
        total = total + reg_weight(config, model.feature_scale) * reg
        parts["reg"] = float(reg.detach())
    if config.linearity_loss > 0 and step % config.linearity_every == 0 and len(intensity) > 1:
        lc = linearity_consistency(model, texels, sample, lights, intensity, mean_texture,
                                   np.random.default_rng([config.seed, step, item[0]]))
        total = total + config.linearity_loss * lc
        parts["lc"] = float(lc.detach())
    d_inputs = None
    if disc is not None:
        from .adversarial import generator_loss, lighting_prompt
        prompt = lighting_prompt(texels, sample.gbuffer, lights, intensity,
                                 float(model.feature_scale), config.shininess, device)
        gan = generator_loss(disc, image, prompt, mask)
        total = total + config.lambda_gan * gan
        parts["gan"] = float(gan.detach())
        d_inputs = (target, image.detach(), prompt, mask)
    return total, parts, d_inputs


def linearity_consistency(model, texels, sample, lights, intensity, mean_texture, rng):
    """Eq. 17: ‖a₁F_l(F¹) + a₂F_l(F²) − F_l(a₁F¹ + a₂F²)‖ (RMS over texels) with F¹, F²
    the features of the two halves of the frame's LEDs (supp. 10.2)."""
    from .geometry import LightInputs
    half = len(intensity) // 2
    a1, a2 = rng.uniform(0, 1, 2)

    def part(sl, weight):
        li = [LightInputs(x.local_light[sl], x.visibility[sl], x.falloff[sl]) for x in lights]
        return render_textures(model, texels, [texels.local_view(k, sample.gbuffer.eye)
                                               for k in range(texels.n_hands)],
                               li, intensity[sl] * weight, sample.poses, mean_texture, False)
    first, second = part(slice(0, half), 1.0), part(slice(half, None), 1.0)
    both = [a1 * f + a2 * s for f, s in zip(first.features, second.features)]
    err = 0.0
    count = 0
    tex = mean_texture.expand(texels.n_hands, -1, -1, -1) \
        if mean_texture.shape[0] == 1 else mean_texture
    from .models import pose_vector
    _, _, joint = model.physical(tex, pose_vector(sample.poses).to(tex.device))
    mods = model.nonlinear(joint, model.config.tex_res)
    for k in range(texels.n_hands):
        modulation = [m[k:k + 1] for m in mods]
        mixed = model.neural(both[k], tex[k], modulation)
        sep = a1 * first.neural[k] + a2 * second.neural[k]
        err = err + ((mixed - sep) ** 2).sum()
        count += mixed.numel()
    return torch.sqrt(err / count + 1e-20)


def evaluate(model, data, config: LinearConfig, device, mean_texture, splits=None,
             every: bool = False) -> dict:
    """Per split {mse, psnr, ssim, mae, samples} (:func:`relight_cli.neural.train.evaluate_splits`);
    the capture's splits also get ``light_path_share``: RMS of (neural − physical-branch
    render) over RMS of the image inside the hand (:func:`learned_share`; ≈ 0 when the
    learned light path is dead and the model is its physical branch)."""
    from .teacher import env_light_inputs
    share = {}
    current = [None]

    def frame(item):
        sample = data.sample(*item)
        lights, weights = lights_of(data, sample.frame)
        pred, pb, _ = render_image(model, data.texels(sample.pose), sample.gbuffer,
                                   sample.poses, lights, weights, mean_texture, physical=True)
        inside = (sample.mask > 0) | (sample.gbuffer.mask > 0)
        num, den = learned_share(pred, pb, sample.image, inside)
        acc = share.setdefault(current[0], [0.0, 0.0])
        acc[0] += num
        acc[1] += den
        return pred.cpu().numpy(), sample.image, sample.mask

    def env(texels, gbuffer, poses, denv):
        lights, weights = env_light_inputs(texels, denv, config.visibility)
        return render_image(model, texels, gbuffer, poses, lights, weights,
                            mean_texture)[0].cpu().numpy()
    names = splits or [s for s, items in data.splits().items()
                       if s in ("heldout", "fully_lit", "env") and items]
    out = {}
    for name in names:                  # one split at a time: the share is per split
        current[0] = name
        out.update(evaluate_splits(model, data, None if every else config.val_samples, frame,
                                   env, [name], tuple(config.env_res)))
    for name, (num, den) in share.items():
        if name in out and den > 0:
            out[name]["light_path_share"] = float(np.sqrt(num / den))
    return out


def learning_rate(config: LinearConfig, step: int) -> float:
    return config.lr if step < config.lr_drop else config.lr_final


class LinearTask:
    """What :func:`relight_cli.neural.train.fit` needs to train URHand's model: T̄ and the
    feature scale on a fresh start, the lr drop before each step, the discriminator's own
    Adam step after it, and gradients averaged by one all-reduce (``ddp = False``).

    ``data`` is one CaptureData or a list of them, one per subject (URHand Sec. 4.3,
    Table 2: one universal model over identities).  The training items are (subject,
    item) pairs over every subject's training items, concatenated in subject order, and
    each step's batch is drawn from them by (seed, step) as for one capture; a sample is
    conditioned on its own subject's T̄ (``mean_textures[subject]``, Fig. 2: "a mean
    texture … for each identity").  ``data`` and ``mean_texture`` are the first
    subject's.  One subject writes exactly the checkpoint it wrote before subjects
    existed (no ``subjects`` / ``mean_textures`` extras)."""

    kind = "linear"
    model_name = "linear"
    desc = "train-teacher (linear)"
    ddp = False

    def __init__(self, data, config: LinearConfig, vgg=None):
        self.datas = list(data) if isinstance(data, (list, tuple)) else [data]
        if not self.datas:
            raise ValueError("give at least one capture")
        self.data = self.datas[0]
        self.config = config
        self.vgg = vgg
        self.items = [(s, item) for s, d in enumerate(self.datas)
                      for item in d.splits()["train"]]
        self.capture_key = self.data.key
        self.pose_dim = self.data.pose_dim
        self.mean_texture = None
        self.mean_textures = None
        self.disc = self.opt_d = None
        self._d_batch = []

    def check(self):
        check_subjects(self.datas)
        for s, d in enumerate(self.datas):
            check_training_frames(d, [item for t, item in self.items if t == s])

    def build(self, device, resume=None):
        config = self.config
        model = URHandModel(config, self.pose_dim).to(device)
        if resume is None:
            self.mean_textures = [torch.from_numpy(albedo_texture(d)).to(device)
                                  for d in self.datas]
            self.mean_texture = self.mean_textures[0]
            model.feature_scale.fill_(feature_scale(self.data) if len(self.datas) == 1
                                      else subjects_feature_scale(self.datas))
        if config.lambda_gan > 0:
            from .adversarial import LightingAwareDiscriminator
            self.disc = LightingAwareDiscriminator(config.gan_width, 2,
                                                   config.gan_conditioned).to(device)
            self.opt_d = torch.optim.Adam(self.disc.parameters(), lr=config.lr,
                                          betas=(0.5, 0.999))
        return model

    def restore(self, resume, device):
        extra = resume["extra"]
        self.mean_texture = extra["mean_texture"].to(device)
        if "subjects" in extra:
            keys = [r["capture_key"] for r in extra["subjects"]]
            if keys != [d.key for d in self.datas]:
                raise ValueError(f"checkpoint was trained on the subjects {', '.join(keys)}, "
                                 f"these captures are {', '.join(d.key for d in self.datas)}")
            self.mean_textures = [extra["mean_textures"][r["mean_texture"]].to(device)
                                  for r in extra["subjects"]]
        elif len(self.datas) == 1:
            self.mean_textures = [self.mean_texture]
        else:
            raise ValueError(f"checkpoint was trained on one subject, not "
                             f"{len(self.datas)}")
        if self.disc is not None:
            self.disc.load_state_dict({k: v.to(device) for k, v in
                                       resume["extra"]["discriminator"].items()})
            self.opt_d.load_state_dict(resume["extra"]["optimizer_discriminator"])

    def before_step(self, optimizer, step):
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(self.config, step)

    def loss(self, net, item, step, device):
        subject, item = item
        loss, parts, d_inputs = sample_loss(net, self.datas[subject], item, self.config, step,
                                            device, self.mean_textures[subject], self.vgg,
                                            self.disc)
        if d_inputs is not None:
            self._d_batch.append(d_inputs)
        return loss, parts

    def after_step(self, step, world):
        batch, self._d_batch = self._d_batch, []
        if self.disc is None:
            return
        from .adversarial import discriminator_loss
        self.opt_d.zero_grad(set_to_none=True)        # drops what L_G left in F_D
        for real, fake, prompt, mask in batch:
            (discriminator_loss(self.disc, real, fake, prompt, mask) / len(batch)).backward()
        if world > 1:
            average_gradients(self.disc, world)
        self.opt_d.step()

    def evaluate(self, model, device, every: bool = False):
        """The first subject's splits (as for one capture); with several subjects also
        ``subject1``, ``subject2`` … (the splits of ``extra.subjects[s]``'s capture, under
        its own T̄): held-out poses of every trained subject.  ``every``: the first
        subject's held-out split, every sample of it."""
        if every:
            return evaluate(model, self.data, self.config, device, self.mean_texture,
                            ["heldout"], every=True)
        out = evaluate(model, self.data, self.config, device, self.mean_texture)
        for s in range(1, len(self.datas)):
            out[f"subject{s}"] = evaluate(model, self.datas[s], self.config, device,
                                          self.mean_textures[s])
        return out

    def extra(self) -> dict:
        from .geometry import hand_records, uv_layout_digest
        out = {"uv_layout": uv_layout_digest(self.data.hand.mesh("fine")),
               "hands": hand_records(self.data.hand),
               "mean_texture": self.mean_texture.detach().cpu()}
        if len(self.datas) > 1:
            out["subjects"] = subject_records(self.datas)
            out["mean_textures"] = torch.stack([t.detach().cpu() for t in self.mean_textures])
        if self.disc is not None:
            out["discriminator"] = {k: v.detach().cpu() for k, v in self.disc.state_dict().items()}
            out["optimizer_discriminator"] = self.opt_d.state_dict()
        return out


def train(data, config: LinearConfig, device: torch.device, resume: dict | None = None,
          vgg=None, provenance: dict | None = None, save=None, show_progress: bool = True,
          log=None) -> TrainResult:
    """Train URHand's model on ``data``'s grouped frames: one CaptureData, or a list of
    them, one per subject (:class:`LinearTask`; URHand Sec. 4.3, Table 2).  Arguments as
    :func:`relight_cli.neural.train.train`; the loop is :func:`relight_cli.neural.train.fit`."""
    return fit(LinearTask(data, config, vgg), config, device, resume, provenance, save,
               show_progress, log)


@torch.no_grad()
def render_lights(model, texels, gbuffer, poses, light_inputs: list, intensity, mean_texture,
                  timing=None, background=0.0) -> torch.Tensor:
    """Inference: [H, W, 3] image of a posed scene under L lights (point lights or an env
    map's directions, :func:`relight_cli.neural.teacher.point_light_inputs` /
    ``env_light_inputs``) in one pass of the model."""
    t0 = time.perf_counter()
    if len(intensity) == 0:
        from .teacher import composite
        n = texels.tex_res
        image = composite([torch.zeros(3, n, n, device=mean_texture.device)] * texels.n_hands,
                          gbuffer, background)
    else:
        image = render_image(model, texels, gbuffer, poses, light_inputs, intensity,
                             mean_texture, background=background)[0]
    if timing is not None:
        timing.add("network", time.perf_counter() - t0)
    return image
