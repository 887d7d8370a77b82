"""Learned models on a capture: each hand rendered by its own model, scored against ground truth.

RelightableHands captures the right and the left hand separately, trains one teacher per
hand, and evaluates right, left and both hands (Sec. 5, Tables 1 and 3): two-hand
sequences are used for evaluation only.  Here a scene of one or two hands is rendered
with one model per hand (:func:`assign_models`: each hand takes the checkpoint trained on
its handedness), every hand's visibility traced against *every* hand of the scene (one
embree scene, :class:`~relight_cli.neural.geometry.PoseTexels`), and the per-hand
textures composited through one camera G-buffer (which resolves the occlusions between
the hands).  Models are teachers (``olat``, the ``ggx`` baseline) or URHand's linear
model.

:func:`evaluate_capture` scores a capture's frames (grouped-light, fully lit) and its
``eval/`` renders under env maps: MSE, PSNR, SSIM and MAE inside the ground-truth hand
mask, and per hand inside that hand's own mask (the capture's per-hand coverage channels,
formats/capture.md, or the G-buffer's where a capture has none).  The study runner and
``relight relight CAPTURE/ --model teacher --checkpoint right.pt --checkpoint left.pt``
call it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np
import torch

from relight_cli.envmap import DEFAULT_GRID
from relight_cli.errors import DataError

from .ceiling import Ceiling, ceiling_of  # noqa: F401
from .scores import _win, attach_ceiling, hand_names, mean_scores, score, spread  # noqa: F401

from .data import LRU
from .teacher import Timing, composite, hand_texture

SPLITS = ("train", "heldout", "grouped", "fully_lit", "env")


@dataclass
class HandModel:
    """A loaded learned model of one or more hands.

    Attributes:
        kind: ``teacher`` (``olat`` / ``ggx``) or ``linear``.
        net: the module (eval mode).  config: its TeacherConfig or LinearConfig.
        mean_texture: T̄ [1, 3, N, N] (ggx, linear) or None.
        sides: handedness of the hands it was trained on (empty: not recorded, a
            checkpoint from before the record existed).
        uv_layouts: the UV layout digest of each trained hand (as rendered).
        layout: the checkpoint's ``uv_layout``, the digest of its training hand's fine
            mesh as rendered ("" when not recorded); checked against a scene's hand in
            either winding, so a checkpoint cannot claim another hand model's layout.
        capture_key: the training capture's key.  pose_dim: pose vector length.
        name: a label for messages (e.g. the checkpoint path).  step: iterations trained.
        subjects: (linear) [(capture key, skin seed or None, T̄ [1, 3, N, N])] of the
            subjects it was trained on (URHand Sec. 4.3; one for a one-capture checkpoint).
        subject: (linear, on a capture) ``seen`` when the capture is one of ``subjects``
            (``mean_texture`` is then that subject's stored T̄), ``unseen`` when not
            (``mean_texture`` is the capture's own T̄, URHand Table 2's unseen subject);
            "" otherwise.
    """

    kind: str
    net: torch.nn.Module
    config: object
    mean_texture: torch.Tensor | None
    sides: list = field(default_factory=list)
    uv_layouts: list = field(default_factory=list)
    capture_key: str = ""
    pose_dim: int = 0
    name: str = ""
    step: int = 0
    layout: str = ""
    subjects: list = field(default_factory=list)
    subject: str = ""

    @property
    def model_name(self) -> str:
        return self.config.model

    @property
    def tex_res(self) -> int:
        return int(self.config.tex_res)

    @property
    def visibility(self) -> bool:
        return bool(self.config.visibility)


def load_hand_model(checkpoint: dict, device="cpu", name: str = "") -> HandModel:
    """A :class:`HandModel` from a read checkpoint (``neural.checkpoints.read_checkpoint``)
    of kind ``teacher`` or ``linear``.  Raises ValueError for a checkpoint that does not
    build (the caller names the file)."""
    from . import registry
    from .checkpoints import load, subjects_from_checkpoint
    kind = checkpoint["kind"]
    spec = registry.for_kind(kind)
    if not spec.one_per_hand:
        per_hand = " or ".join(registry.names(one_per_hand=True))
        raise ValueError(f"a {kind!r} checkpoint is not a per-hand model (use a {per_hand} "
                         f"checkpoint)")
    net, config, mean = load(checkpoint, device)
    subjects = subjects_from_checkpoint(checkpoint, device) if spec.subjects else []
    extra = checkpoint.get("extra", {})
    hands = extra.get("hands") or []
    if isinstance(hands, str):
        hands = json.loads(hands)
    sides = [str(h["side"]) for h in hands]
    layouts = [str(h.get("uv_chart", "")) for h in hands]
    if not hands and extra.get("uv_layout"):
        layouts = [str(extra["uv_layout"])]
    return HandModel(kind, net, config, mean, sides, layouts, str(checkpoint["capture_key"]),
                     int(checkpoint["pose_dim"]), name, int(checkpoint["step"]),
                     str(extra.get("uv_layout") or ""),
                     subjects)


def resample_texture(texture: np.ndarray, n: int) -> np.ndarray:
    """[3, M, M] → [3, n, n]: area averaging when M is a multiple of n (a stored T̄ at a
    finer resolution than the model's), else bilinear at the texel centres."""
    t = np.asarray(texture, np.float64)
    m = t.shape[-1]
    if m == n:
        return t.astype(np.float32)
    if m % n == 0:
        f = m // n
        return t.reshape(3, n, f, n, f).mean((2, 4)).astype(np.float32)
    from relight_cli.render.appearance import bilinear
    c = (np.arange(n) + 0.5) / n
    u, v = np.meshgrid(c, 1 - c)
    out = bilinear(np.transpose(t, (1, 2, 0)), np.stack([u.ravel(), v.ravel()], 1))
    return np.transpose(out.reshape(n, n, 3), (2, 0, 1)).astype(np.float32)


def with_own_subject(models: list, texture: np.ndarray) -> list:
    """Each model conditioned on a subject's own T̄ ([3, M, M], e.g. a personalised
    hand.npz's ``mean_texture``; URHand Sec. 5.4: a new identity's mean texture fed to
    the universal model without finetuning), resampled to its resolution; ``subject``
    becomes ``own``.  Models that take no T̄ (teachers without one) are returned as they
    are."""
    import dataclasses

    from . import registry
    out = []
    for m in models:
        if not registry.for_kind(m.kind).subjects or m.mean_texture is None:
            out.append(m)
            continue
        t = torch.from_numpy(resample_texture(texture, m.tex_res))[None]
        out.append(dataclasses.replace(m, mean_texture=t.to(m.mean_texture.device),
                                       subject="own"))
    return out


def assign_models(models: list, sides: list) -> list:
    """The model of each hand of a scene whose hands have handedness ``sides``.

    One model renders every hand (as a teacher trained on one hand renders a scene of
    two); with several, each hand takes the one model trained on its handedness.
    Raises ValueError when a hand has no model, or two.
    """
    if not models:
        raise ValueError("give at least one model")
    if len(models) == 1:
        return [models[0]] * len(sides)
    for m in models:
        if not m.sides:
            raise ValueError(f"{m.name or 'a checkpoint'} does not record which hand it was "
                             f"trained on (an older checkpoint): give it alone")
    out = []
    for k, side in enumerate(sides):
        matches = [m for m in models if side in m.sides]
        if not matches:
            raise ValueError(f"no checkpoint was trained on the {side} hand (hand {k} of the "
                             f"scene); the checkpoints know {', '.join(sorted({s for m in models for s in m.sides}))}")
        if len(matches) > 1:
            raise ValueError(f"{len(matches)} checkpoints were trained on the {side} hand: "
                             f"{', '.join(m.name or '?' for m in matches)}; give one per hand")
        out.append(matches[0])
    unused = [m for m in models if all(m is not a for a in out)]
    if unused:
        raise ValueError(f"{unused[0].name or 'a checkpoint'} ({'/'.join(unused[0].sides)} "
                         f"hand) matches no hand of the scene")
    return out


def check_hands(models: list, hand) -> None:
    """Refuse a scene a hand's model cannot render: another joint count, or another UV
    chart than the one its texture was learned on (ValueError naming the hand), or a
    checkpoint whose ``uv_layout`` contradicts its own hands record (ValueError whose
    ``path`` attribute is the model's name: the checkpoint is at fault)."""
    from .geometry import hand_records, uv_layout_digest, uv_layout_digests
    records = hand_records(hand)
    windings = uv_layout_digests(hand.mesh("fine"))
    for k, (model, record) in enumerate(zip(models, records)):
        label = model.name or "the model"
        if (hand.n_joints - 1) * 3 != model.pose_dim:
            raise ValueError(f"the hand has {hand.n_joints} joints; {label} was trained on "
                             f"{model.pose_dim // 3 + 1}")
        if model.sides:
            ok = record["uv_chart"] in model.uv_layouts
        else:   # an older checkpoint: the digest of its training hand's model mesh
            ok = not model.uv_layouts or uv_layout_digest(hand.mesh("fine")) in model.uv_layouts
        if ok and model.layout and model.layout not in windings:
            err = ValueError(f"the checkpoint's uv_layout is not the UV layout of the hand "
                             f"its hands record names (hand {k} of the scene matches the "
                             f"record): a damaged or edited checkpoint")
            err.path = model.name      # the checkpoint is at fault, not the scene
            raise err
        if not ok:
            raise ValueError(f"hand {k}'s UV layout differs from the one {label} learned its "
                             f"texture on (another hand model?)")


def scene_texels(models: list, make) -> list:
    """Per hand, the texel G-buffer its model needs: ``make(tex_res, visibility)`` →
    PoseTexels, called once per distinct (tex_res, visibility) among ``models``."""
    cache = {}
    out = []
    for m in models:
        key = (m.tex_res, m.visibility)
        if key not in cache:
            cache[key] = make(*key)
        out.append(cache[key])
    return out


def point_inputs(model, texels, k: int, positions):
    """Hand k's LightInputs of point lights at ``positions`` [L, 3] for ``model``."""
    return texels.point_lights(k, positions, visibility=model.visibility)


def env_inputs(model, texels, k: int, denv):
    """(hand k's LightInputs, [M', 3] weights L Δω) of a discretized env map's lit
    directions for ``model``."""
    lit = np.nonzero(denv.lit)[0]
    return (texels.directional_lights(k, denv.directions[lit], visibility=model.visibility),
            denv.radiance[lit] * denv.solid_angle[lit, None])


@torch.no_grad()
def model_texture(model: HandModel, texels, k: int, pose, light_inputs, intensity, eye,
                  device="cpu", progress=None, timing: Timing | None = None) -> torch.Tensor:
    """Hand k's texture [3, N, N] under L lights (LightInputs of hand k, [L, 3] weights)
    seen from ``eye``, by a teacher (per-light passes summed, Eq. 2) or the linear model
    (one pass over the summed features)."""
    from .registry import for_kind
    intensity = np.asarray(intensity, np.float64)
    if not for_kind(model.kind).sums_features:      # one pass per light, summed (Eq. 2)
        cfg = model.config
        return hand_texture(model.net, texels, k, pose, light_inputs, intensity, cfg.visibility,
                            cfg.falloff, eye, device, mean_texture=model.mean_texture,
                            progress=progress, timing=timing)
    import time

    from .linear import render_textures
    t0 = time.perf_counter()
    if len(intensity) == 0:
        out = torch.zeros(3, texels.tex_res, texels.tex_res, device=device)
    else:
        one = texels.select(k)
        out = render_textures(model.net, one, [one.local_view(0, eye)], [light_inputs],
                              intensity, np.asarray(pose)[None], model.mean_texture,
                              physical=False).neural[0]
    if timing is not None:
        timing.add("network", time.perf_counter() - t0)
    if progress is not None:
        progress(len(intensity))
    return out


@torch.no_grad()
def render_scene(models: list, texels: list, gbuffer, poses, light_inputs: list, intensity,
                 device="cpu", progress=None, timing: Timing | None = None,
                 background=0.0) -> torch.Tensor:
    """[H, W, 3] image of a posed scene, hand k by ``models[k]``.

    Args:
        models: per hand its :class:`HandModel`.  texels: per hand the PoseTexels of the
            scene its model needs (:func:`scene_texels`).
        gbuffer: the camera's G-buffer of every hand.  poses: [H, J, 3].
        light_inputs: per hand its LightInputs of the same L lights (from its own texels).
        intensity: [L, 3] b_i, or per hand [L_k, 3] (env maps: each model's lit directions).
    """
    textures = []
    for k, model in enumerate(models):
        weights = intensity[k] if isinstance(intensity, (list, tuple)) else intensity
        textures.append(model_texture(model, texels[k], k, poses[k], light_inputs[k], weights,
                                      gbuffer.eye, device, progress, timing))
    return composite(textures, gbuffer, background)


class LambertBaseline(torch.nn.Module):
    """The strongest non-learned teacher we test learned models against.

    Per light i and texel: C_i = s ⊙ T̄ · max(l_z, 0) · h_i, with T̄ the capture's mean
    texture (:meth:`~relight_cli.neural.data.CaptureData.mean_texture`: what the cameras
    saw under the fully lit frames, ≈ albedo), l_z the light direction's cosine in the
    texel frame, h_i the ray-traced visibility — the teacher's own inputs — and one scale
    per colour channel s fitted by least squares on the training images
    (:func:`fit_lambert_baseline`): Lambertian skin with correct shadows and its
    measured colour.  A learned teacher has to beat it on held-out data to show it
    learned more than that; a dead network (frozen, or never trained) does not.

    Called like a teacher (``forward(inputs, pose, hand_of, mean_texture)``), so it
    renders through the same :func:`~relight_cli.neural.teacher.render_sample`,
    compositing and scoring.
    """

    kind = "olat"

    def __init__(self, mean_texture: torch.Tensor):
        super().__init__()
        self.register_buffer("mean", torch.as_tensor(mean_texture, dtype=torch.float32))
        self.register_buffer("scale", torch.ones(3))

    def forward(self, inputs, pose, hand_of, mean_texture=None, return_raw: bool = False):
        mean = self.mean if self.mean.shape[0] == 1 else self.mean[hand_of]
        cosine = torch.clamp(inputs[:, 2:3], min=0) * inputs[:, 6:7]
        colour = self.scale[None, :, None, None] * mean * cosine
        return (colour, None) if return_raw else colour


def fit_lambert_baseline(data, items: list, max_items: int = 24) -> LambertBaseline:
    """:class:`LambertBaseline` of ``data`` (a CaptureData) with s fitted on at most
    ``max_items`` evenly spaced training ``items`` (inside the ground-truth mask)."""
    from .teacher import render_sample
    base = LambertBaseline(torch.from_numpy(data.mean_texture()))
    num, den = np.zeros(3), np.zeros(3)
    with torch.no_grad():
        for i in spread(len(items), max_items):
            sample = data.sample(*items[i])
            pred = render_sample(base, sample).numpy()
            region = sample.mask > 0.5
            x, y = pred[region].astype(np.float64), sample.image[region].astype(np.float64)
            num += (x * y).sum(0)
            den += (x * x).sum(0)
    base.scale.copy_(torch.from_numpy(num / np.maximum(den, 1e-30)).float())
    return base


class CaptureEvaluator:
    """Renders and scores a capture's samples with one model per hand.

    Args:
        capture: a capture folder (holding capture.json) or a ``CaptureData``.
        models: :class:`HandModel` list (one for every hand, or one per handedness).
        device: torch device.  aa: G-buffer samples per pixel axis (default: a given
            CaptureData's, else the first model's).  env_res: (H, W) grid the models
            integrate env maps over.
        cache_poses: poses whose texel G-buffers stay cached.
    """

    def __init__(self, capture, models: list, device="cpu", aa: int | None = None,
                 env_res=DEFAULT_GRID, cache_poses: int = 8):
        from relight_cli.hand.scene import handedness

        from .data import CaptureData
        if not models:
            raise ValueError("give at least one model")
        first = models[0]
        given = capture if isinstance(capture, CaptureData) else None
        self.device = device
        self.env_res = tuple(env_res)
        if aa is None and given is not None:
            aa = given.aa
        self.aa = int(aa) if aa else 0          # 0: the capture's own sampling
        folder = given.folder if given is not None else capture
        self._data = {}
        self._make_data = lambda tex_res, vis: CaptureData(
            folder, tex_res, self.aa, vis, holdout=getattr(first.config, "holdout", 0.25),
            cache_poses=cache_poses)
        base = given or self._make_data(first.tex_res, first.visibility)
        self.aa = base.aa
        self.data = base
        self.sampling = dict(base.sampling)
        self.ceiling = Ceiling(base)
        self._data[(base.tex_res, base.visibility)] = base
        sides = handedness(base.hand)
        self.models = assign_models(models, sides)
        try:
            check_hands(self.models, base.hand)
            if base.eval_hand is not None:
                check_hands(self.models, base.eval_hand)
        except ValueError as exc:
            raise DataError(str(exc), getattr(exc, "path", None) or base.hand_path) from None
        self.names = hand_names(sides)
        self._env_inputs = LRU(4)
        self._envs = {}
        self.models = self._condition_on_subject(self.models)

    def _condition_on_subject(self, models: list) -> list:
        """Each linear model conditioned on this capture's subject (URHand Sec. 4, Fig. 2:
        T̄ is an input per identity): the stored T̄ of the checkpoint's subject whose
        capture key is this capture's (``subject = "seen"``), else this capture's own T̄
        (:func:`~relight_cli.neural.linear_train.albedo_texture`, as at training;
        ``subject = "unseen"``) — URHand scores an unseen identity given its own mean
        texture (Table 2's "unseen subject"; Sec. 5.4 feeds a new person's T̄ without
        finetuning), never a trained subject's.  Teachers are returned as they are."""
        import dataclasses

        from . import registry
        key = self.data.key
        made = {}
        out = []
        for m in models:
            if not registry.for_kind(m.kind).subjects or m.mean_texture is None:
                out.append(m)
                continue
            if id(m) not in made:
                subjects = m.subjects or [(m.capture_key, None, m.mean_texture)]
                device = m.mean_texture.device
                stored = [t for k, _, t in subjects if k == key]
                if stored:
                    made[id(m)] = dataclasses.replace(m, mean_texture=stored[0].to(device),
                                                      subject="seen")
                else:
                    from .linear_train import albedo_texture
                    own = albedo_texture(self.data_for(m.tex_res, m.visibility))
                    made[id(m)] = dataclasses.replace(
                        m, mean_texture=torch.from_numpy(own).to(device), subject="unseen")
            out.append(made[id(m)])
        return out

    # ---------------------------------------------------------------- pieces

    def data_for(self, tex_res: int, visibility: bool):
        key = (tex_res, visibility)
        if key not in self._data:
            self._data[key] = self._make_data(tex_res, visibility)
        return self._data[key]

    def texels(self, pose: int, held_out: bool) -> list:
        return scene_texels(self.models, lambda n, v: self.data_for(n, v).texels(pose, held_out))

    def default_splits(self) -> list:
        """Held-out grouped frames of a capture a model trained on, every grouped frame of
        another one; fully lit frames; env renders (the non-empty ones)."""
        trained_here = any(m.capture_key == self.data.key or m.subject == "seen"
                           for m in self.models)
        names = ["heldout" if trained_here else "grouped", "fully_lit", "env"]
        splits = self.data.splits()
        return [n for n in names if splits.get(n)]

    def env_map(self, name: str):
        if name not in self._envs:
            from relight_cli.envmap import discretize_env
            self._envs[name] = discretize_env(self.data.env_map(name), *self.env_res)
        return self._envs[name]

    # ---------------------------------------------------------------- one sample

    def predict(self, item, timing: Timing | None = None):
        """(prediction [H, W, 3], ground truth, mask, per-hand masks [n, H, W] or None)
        of one split item: a capture (frame, camera) or an ``("env", render record)``."""
        from relight_cli.formats import capture as C
        data = self.data
        n = data.n_hands
        if item[0] == "env":
            render = item[1]
            try:
                camera = data.capture.camera(render["camera"])
            except KeyError:
                raise DataError(f"evaluation render names unknown camera "
                                f"{render['camera']!r}", data.index_path) from None
            gt, mask, hands = C.read_image_hands(os.path.join(data.folder, render["image"]),
                                                 camera, n)
            pose, held_out = int(render["pose"]), True
            texels = self.texels(pose, True)
            denv = self.env_map(render["env"])
            inputs = self._env_inputs.get_or((pose, render["env"]), lambda: [
                env_inputs(m, texels[k], k, denv) for k, m in enumerate(self.models)])
            lights = [li for li, _ in inputs]
            intensity = [w for _, w in inputs]
        else:
            frame = data.frame(item[0])
            camera = data.capture.camera(item[1])
            path = os.path.join(data.folder, C.image_path(frame.index, camera.name))
            if not os.path.isfile(path):
                raise DataError(f"frame {frame.index} lists camera {camera.name!r} but its "
                                f"image is missing", path)
            gt, mask, hands = C.read_image_hands(path, camera, n)
            pose, held_out = frame.pose, False
            texels = self.texels(pose, False)
            lights = []
            for k, m in enumerate(self.models):
                per_hand = self.data_for(m.tex_res, m.visibility).light_inputs(
                    pose, frame.lights_on)
                lights.append(per_hand[k])
            intensity = data.capture.light_intensity[np.asarray(frame.lights_on, np.int64)]
        gbuffer = data.gbuffer(pose, camera, held_out)
        pred = render_scene(self.models, texels, gbuffer, data.poses(pose, held_out), lights,
                            intensity, self.device, timing=timing)
        if hands is None and n > 1:
            hands = np.stack([gbuffer.coverage(k) * (mask > 0.5) for k in range(n)])
        self._last = (texels, gbuffer)
        return pred.cpu().numpy(), gt, mask, hands

    def score(self, item, with_ceiling: bool = False):
        """:func:`score` of one item; with ``with_ceiling`` the pair (model's, ceiling's:
        {} where the capture has no stage to rebuild)."""
        pred, gt, mask, hands = self.predict(item)
        names = self.names if self.data.n_hands > 1 else []
        ours = score(pred, gt, mask, hands, names)
        if not with_ceiling:
            return ours
        best = {}
        if self.ceiling.available:
            texels, gbuffer = self._last
            best = self.ceiling.score(item, texels, gbuffer, gt, mask, hands, names)
        return ours, best

    # ---------------------------------------------------------------- splits

    def evaluate(self, splits=None, max_samples: int | None = None, progress=None) -> dict:
        """{split: {mse, psnr, ssim, mae, samples[, hand name: {...}]}}: means over the
        split's samples (at most ``max_samples`` evenly spaced ones; None: all)."""
        all_splits = self.data.splits()
        names = list(splits) if splits else self.default_splits()
        for name in names:
            if name not in SPLITS:
                raise ValueError(f"unknown split {name!r}; use {', '.join(SPLITS)}")
        out = {}
        for name in names:
            items = all_splits.get(name) or []
            if not items:
                continue
            rows, best = [], []
            for i in spread(len(items), max_samples):
                ours, ceiling = self.score(items[i], with_ceiling=True)
                rows.append(ours)
                best.append(ceiling)
                if progress is not None:
                    progress(1)
            scores = attach_ceiling(mean_scores(rows), best)
            if scores:
                out[name] = scores
        return out


def evaluate_capture(capture, models: list, splits=None, max_samples: int | None = None,
                     device="cpu", aa: int | None = None, env_res=DEFAULT_GRID,
                     progress=None) -> dict:
    """Score learned models (one per hand, or one for all) on a capture.

    Args:
        capture: capture folder or CaptureData (e.g. a two-hand capture from
            ``synth-capture builtin:two``).
        models: :class:`HandModel` list (:func:`load_hand_model` of each checkpoint); a
            linear model is conditioned on the capture's subject: its stored T̄ when it
            trained on the capture, else the capture's own T̄ (an unseen subject, URHand
            Table 2; :meth:`CaptureEvaluator._condition_on_subject`).
        splits: among :data:`SPLITS` (``grouped``: every grouped-light frame, for a
            capture no model trained on); default :meth:`CaptureEvaluator.default_splits`.
        max_samples: per split, at most this many evenly spaced samples (None: all).
        device, aa, env_res: see :class:`CaptureEvaluator`.
        progress: optional callable(n) per scored sample.

    Returns:
        {split: {"mse", "psnr", "ssim", "mae", "samples", and for two hands "right",
        "left" (or hand0, hand1): the same inside that hand's mask}}; MSE in the
        capture's linear radiance units (RelightableHands' tables print MSE × 10³).
    """
    return CaptureEvaluator(capture, models, device, aa, env_res).evaluate(
        splits, max_samples, progress)
