"""The ceiling of a learned model: the perfect texture at its resolution, scored through the
same compositing, pixel sampling and metrics as the model (DESIGN.md "How a learned model
is judged").  :func:`ceiling_of` gives a capture's, made once per CaptureData.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from types import SimpleNamespace

import numpy as np
import torch

from relight_cli.progress import LateProgress

from .data import LRU
from .scores import score
from .teacher import composite


def ceiling_of(data) -> "Ceiling":
    """``data``'s :class:`Ceiling` (a CaptureData; made once and kept on it)."""
    made = data.__dict__.get("_ceiling")
    if made is None:
        made = data.__dict__["_ceiling"] = Ceiling(data)
    return made


class Ceiling:
    """The perfect-texture score of a capture's samples: a learned model's ceiling.

    For a synthetic capture (its capture.json records every stage setting,
    :func:`relight_cli.render.capture.stage_settings`), the stage's own shader is evaluated
    at the N×N texel centres of the model's texture (:class:`~relight_cli.render.capture.
    StageShader`), and that texture goes through the model's own compositing
    (:func:`~relight_cli.neural.teacher.composite` on the same camera G-buffer, i.e. the
    same pixel sampling) and the same :func:`score`: what a texture of that resolution
    scores when it holds the exact answer at its texel centres.  It is not a strict
    bound — a texture fitted through the bilinear lookup (pre-filtered) can beat point
    samples by a fraction of a dB — but a model far below it has not learned what its
    resolution allows.  Real captures have no ceiling (:attr:`available` False).

    Args:
        data: the :class:`~relight_cli.neural.data.CaptureData` (its hand, eval hand,
            lights and env maps).

    Attributes:
        quiet: True (the default) keeps :meth:`predict` silent; False shows progress over
            the texels shaded when a sample's ceiling looks long (an env render's GGX lobe
            over every lit direction: minutes per sample at 256², 2 cores), on stderr.
        log: callable(str) or None: told (unless quiet) when an env map's lighting of a
            pose is traced, a silent stretch of tens of seconds at the stage's size.
    """

    #: Texel centres shaded per call of the stage's shader: each is shaded on its own
    #: (a one-sample "pixel"), so the chunks change no value (tests/neural/test_ceiling.py),
    #: only when progress is said, and they are faster: an env render's texel-visibility
    #: lookup grows with shaded points × texels (one 128² env sample of the demo capture:
    #: 64.5 s in one call, 11.8 s in chunks, 2 shared cores).
    CHUNK = 4096
    #: a sample's ceiling expected to take this long (s) shows progress (unless quiet)
    PROGRESS_SECONDS = 5.0

    def __init__(self, data):
        from relight_cli.formats.lights_json import Lights
        from relight_cli.render.capture import StageShader, stage_settings

        self.data = data
        settings = stage_settings(data.capture.settings)
        self.shader = None
        if settings is not None:
            lights = Lights.from_radiant_intensity(
                np.asarray(data.capture.light_positions, np.float64),
                np.asarray(data.capture.light_intensity, np.float64))
            self.shader = StageShader(data.hand, settings, lights)
        self._lighting = LRU(2)
        self._scores = {}
        self.quiet = True
        self.log = None

    @property
    def available(self) -> bool:
        return self.shader is not None

    def _lit(self, pose: int, held_out: bool, lights_on=None, env_name=None):
        def make():
            if env_name is not None and not self.quiet and self.log is not None:
                # tens of seconds at the stage's texture size, with no unit to count
                self.log(f"ceiling: tracing the stage's lighting of held-out pose {pose} under "
                         f"{env_name} at its texels (once per pose and map)")
            renderer = self.shader.renderer(self.data.meshes(pose, held_out))
            if env_name is not None:
                return renderer, renderer.light(env=self.data.env_map(env_name))
            return renderer, renderer.light(self.shader.lights.subset(list(lights_on)))
        key = (held_out, pose, env_name, None if lights_on is None else tuple(lights_on))
        return self._lighting.get_or(key, make)

    def predict(self, item, texels: list, gbuffer) -> np.ndarray:
        """[H, W, 3] image of the perfect textures of ``item`` (a capture (frame, camera)
        or an ``("env", render record)``), hand k's at the texel centres of ``texels[k]``
        (a PoseTexels of the scene at that hand model's N), through ``gbuffer``."""
        if item[0] == "env":
            render = item[1]
            renderer, lighting = self._lit(int(render["pose"]), True, env_name=render["env"])
        else:
            frame = self.data.frame(item[0])
            renderer, lighting = self._lit(frame.pose, False, lights_on=frame.lights_on)
        surfaces = [texels[k].surfaces[k] for k in range(len(texels))]
        radiance = self._texel_radiance(renderer, lighting, surfaces, gbuffer.eye)
        textures = [torch.from_numpy(texels[k].to_maps(k, radiance[k].astype(np.float32)))
                    for k in range(len(texels))]
        return composite(textures, gbuffer).numpy()

    def _texel_radiance(self, renderer, lighting, surfaces, eye) -> list:
        """The stage's texel_radiance of ``surfaces``, in chunks of :data:`CHUNK` texel
        centres, with progress over them when long (unless :attr:`quiet`)."""
        sizes = [len(s.points) for s in surfaces]
        bar = LateProgress(sum(sizes), "ceiling", "ceiling texels", self.quiet,
                           self.PROGRESS_SECONDS)
        out = []
        for k, surface in enumerate(surfaces):
            parts = []
            for lo in range(0, sizes[k], self.CHUNK):
                part = [SimpleNamespace(points=s.points[:0], normals=s.normals[:0],
                                        uv=s.uv[:0], faces=np.zeros(0, np.int64))
                        for s in surfaces]
                cut = slice(lo, lo + self.CHUNK)
                part[k] = SimpleNamespace(points=surface.points[cut],
                                          normals=surface.normals[cut], uv=surface.uv[cut],
                                          faces=surface.raster.face[surface.inside][cut])
                parts.append(self.shader.texel_radiance(renderer, lighting, part, eye)[k])
                bar.update(len(parts[-1]))
            out.append(np.concatenate(parts) if parts else np.zeros((0, 3)))
        bar.close()
        return out

    def score(self, item, texels: list, gbuffer, gt, mask, hand_masks=None,
              names=None) -> dict:
        """:func:`score` of :meth:`predict`, cached per item, texture sizes, sampling and
        the scored pixels: on this Ceiling, and process-wide by the capture's key, so a
        second model of the same capture in one process (a study's rows, the runs of a
        test session, ``relight CAPTURE/`` after training) does not shade it again."""
        ident = ("env", item[1]["image"]) if item[0] == "env" else tuple(item)
        key = (ident, tuple(t.tex_res for t in texels), gbuffer.spp, gbuffer.width)
        if key not in self._scores:
            shared = (self.data.key, *key, gbuffer.height, _digest(gt, mask, hand_masks, names))
            if shared not in _SHARED:
                pred = self.predict(item, texels, gbuffer)
                _SHARED[shared] = score(pred, gt, mask, hand_masks, names)
                while len(_SHARED) > _SHARED_SIZE:
                    _SHARED.popitem(last=False)
            self._scores[key] = _SHARED[shared]
        return dict(self._scores[key])


# Ceiling scores shared by every Ceiling of this process (see Ceiling.score): a few
# hundred bytes each, bounded.
_SHARED_SIZE = 4096
_SHARED: OrderedDict = OrderedDict()


def _digest(*arrays) -> str:
    """SHA-256 of the values that were scored (so a changed image is a new entry)."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
        elif isinstance(a, (list, tuple)):
            h.update(_digest(*a).encode())
        elif isinstance(a, str):
            h.update(a.encode())
        else:
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()
