"""Distillation: RelightableHands' student trained on its teacher's renders under env maps.

**Pseudo ground truth** (Sec. 4.2): for every (pose, camera) the teacher's per-direction
textures C_m (m over the 16×32 grid, each a distant light with its own ray-traced
visibility) are computed once; an env map's target texture is then Σ_m b_m C_m with
b_m = L_m Δω_m — exactly :func:`relight_cli.neural.teacher.render_lights`' env render,
but reusable for every env map and rotation.  Cost: M × 3 × N_t² float32 per hand and
(pose, camera) — 6.3 MB at the tiny teacher's 32², 6.4 GB at the paper's 1024² — kept in
memory up to ``cache_mb``, then in ``--cache DIR`` (``.npy`` files, memory-mapped), else
recomputed.

**Env maps**: a list of (name, DiscreteEnv), split into training and evaluation maps
(a seeded permutation; ``env_holdout`` of them, at least one, are never trained on);
training maps are augmented by rotations about +Y by whole longitude steps — a column
roll of the lat-long grid, which is an exact rotation of the discretized map.  With
``env_augment: mix`` (ours; the paper's ``paper`` trains on the maps as given) each
sample's map is instead synthesized from the training maps (:func:`mix_env`: mixtures,
rotations, mirror images, tints, a sun cell): the paper distills on 2,560 maps, a capture
here comes with a handful, and a student that sees only those learns them rather than
lighting (benchmarks/results/converged/student_env.md measures it).  Every synthesized
map is a non-negative combination of grid radiances, so its pseudo ground truth is as
exact and as cheap as a given map's.

**Scale**: each sample is normalized by its env map's mean radiance s = Σ_m ℓ(L_m) Δω_m
/ 4π (ℓ = mean of RGB): features and target are divided by s and the predicted
texture multiplied back.  The paper trains on env maps of one exposure; with the
normalization the student is exactly scale-equivariant (a 10× brighter env gives a
10× brighter render), and bright and dim maps weigh alike in the loss.

**Loss** (Sec. 4.3): the paper compares the student's render with the teacher's, in
image space over the hand's pixels (``loss_space: image``).  ``loss_space: texture``
(ours) compares the textures themselves — the teacher's for the sample's camera,
Σ_m b_m C_m, which the pseudo ground truth has anyway — over every texel inside the UV
charts: every texel is supervised on every sample, where an image supervises the texels
its camera sees, each as often as it covers pixels.  Measured on DRAM
(benchmarks/results/converged/student_dram_b8/: its light path trains, a tie on the
scores) and on the ``cpu`` preset's linear-head student
(benchmarks/results/converged/student_linear_tex/, three seeds: 22.99 against 28.02 dB on
the consistent truth, worse): the texels a camera does not see have the teacher at view
directions behind the surface, where it never trained, as targets, and fitting them
costs the student the texels the camera sees.

**Student inputs**: bake-features' own pipeline (:class:`relight_cli.bake.PoseFeatures`,
coarse proxy, visibility traced once per pose) under the (rotated) env map, seen from
the camera — diffuse + Phong 16/32/64 texel maps.  DRAM's input: the env map rotated
into the wrist's frame (the root joint's world rotation), nearest texel of the 16×32
grid, log1p(L/s).
"""

from __future__ import annotations

import hashlib
import os
import sys
from collections import OrderedDict

import numpy as np
import torch

from relight_cli.errors import DataError

from .data import LRU, CaptureData, assemble_inputs
from .losses import masked_mse, neg_weight, negativity
from .models import pose_vector
from .student import build_student
from .teacher import composite


# ---------------------------------------------------------------- env maps


def split_envs(names: list[str], holdout: float, seed: int, source: str = "") -> tuple:
    """(training indices, evaluation indices) of ``names``: a seeded permutation, the
    evaluation maps never trained on.  Raises DataError when no training map is left."""
    n = len(names)
    n_eval = int(round(holdout * n))
    if holdout > 0 and n >= 2:
        n_eval = max(1, n_eval)
    order = np.random.default_rng([int(seed), 7]).permutation(n)
    eval_idx = sorted(int(i) for i in order[:n_eval])
    train_idx = sorted(int(i) for i in order[n_eval:])
    if not train_idx:
        raise DataError(f"no training env maps left after holding out {n_eval} of {n} for "
                        f"evaluation (give more --envs or a smaller env_holdout)", source)
    return train_idx, eval_idx


def rotate_env(denv, steps: int):
    """The discretized env rotated about +Y by ``steps`` longitude cells (exact).

    OpenEXR's lat-long grid has end-point pixel centres: columns 0 and W−1 both lie on
    the ±π seam, each a half-width cell, together one full cell.  The W−1 distinct
    longitude cells (spacing 2π/(W−1)) are rolled as a ring, the seam cell carrying the
    area-weighted mean of its two halves and giving it back to both, so the map turns
    by steps·2π/(W−1) and its power Σ L Δω is kept exactly.
    """
    from relight_cli.envmap import DiscreteEnv
    h, w = denv.height, denv.width
    if steps % (w - 1) == 0:
        return denv
    grid = denv.radiance.reshape(h, w, 3)
    omega = denv.solid_angle.reshape(h, w)
    ring = grid[:, :w - 1].copy()
    a0, a1 = omega[:, :1, None], omega[:, w - 1:, None]
    ring[:, :1] = (grid[:, :1] * a0 + grid[:, w - 1:] * a1) / np.maximum(a0 + a1, 1e-300)
    ring = np.roll(ring, int(steps), axis=1)
    out = np.concatenate([ring, ring[:, :1]], axis=1).reshape(-1, 3)
    return DiscreteEnv(denv.directions, denv.solid_angle, out, h, w,
                       f"{denv.name}@{int(steps)}")


def mirror_env(denv):
    """The discretized env mirrored in longitude (φ → −φ: the grid's columns reversed).
    Exact: lat-long pixel centres are symmetric about φ = 0 and a cell's solid angle
    depends on its row only, so the mirrored grid is another env map's exact
    discretization with the same power."""
    from relight_cli.envmap import DiscreteEnv
    h, w = denv.height, denv.width
    grid = denv.radiance.reshape(h, w, 3)[:, ::-1]
    return DiscreteEnv(denv.directions, denv.solid_angle, grid.reshape(-1, 3).copy(), h, w,
                       f"{denv.name}~")


#: ``env_augment: mix``: at most this many training maps per synthesized env map
MIX_MAPS = 3
#: probability of a sun cell, its power as a share of the mixture's (log-uniform range),
#: and the log-normal spread of the per-map and sun tints
MIX_SUN_P, MIX_SUN_SHARE, MIX_TINT = 0.5, (0.1, 3.0), 0.15


def mix_env(envs: list, rng: np.random.Generator, rotations: bool = True):
    """A random env map synthesized from the training maps ``envs`` (``env_augment: mix``).

    1 to :data:`MIX_MAPS` maps drawn with replacement, each rotated about +Y by a random
    whole longitude step (when ``rotations``), mirrored with probability ½, tinted by a
    per-channel log-normal factor (σ :data:`MIX_TINT`, mean channel 1) and weighted by
    U(0.2, 1) over its own mean radiance (so a dim map is not drowned by a bright one);
    then, with probability :data:`MIX_SUN_P`, one grid cell (drawn ∝ its solid angle:
    uniform on the sphere) gets a "sun" carrying a log-uniform share in
    :data:`MIX_SUN_SHARE` of the mixture's power.  Every operation is a non-negative
    linear map of grid radiances, so the teacher's pseudo ground truth Σ_m b_m C_m of the
    result is exact and costs no teacher pass: the paper trains on 2,560 real maps, a
    capture here comes with a handful."""
    from relight_cli.envmap import DiscreteEnv
    first = envs[0]
    total = np.zeros_like(first.radiance)
    for _ in range(int(rng.integers(1, MIX_MAPS + 1))):
        env = envs[int(rng.integers(len(envs)))]
        if rotations:
            env = rotate_env(env, int(rng.integers(env.width - 1)))
        if rng.random() < 0.5:
            env = mirror_env(env)
        tint = np.exp(rng.normal(0.0, MIX_TINT, 3))
        total += env.radiance * (tint / tint.mean()) * (rng.uniform(0.2, 1.0) / env_scale(env))
    omega = first.solid_angle
    if rng.random() < MIX_SUN_P:
        power = float((total.mean(1) * omega).sum())
        m = int(rng.choice(len(omega), p=omega / omega.sum()))
        share = float(np.exp(rng.uniform(*np.log(MIX_SUN_SHARE))))
        tint = np.exp(rng.normal(0.0, MIX_TINT, 3))
        total[m] += (tint / tint.mean()) * share * power / omega[m]
    return DiscreteEnv(first.directions, omega, total, first.height, first.width, "mix")


def env_scale(denv) -> float:
    """Mean radiance s = Σ_m mean_rgb(L_m) Δω_m / 4π (1 for a uniform unit env)."""
    s = float((denv.radiance.mean(1) * denv.solid_angle).sum() / (4 * np.pi))
    return s if s > 0 else 1.0


def wrist_env(denv, rotation: np.ndarray) -> np.ndarray:
    """[H·W·3] radiance of the env seen in a frame with world-from-frame ``rotation``:
    the value at grid direction d is the env's (nearest texel) along R·d."""
    from relight_cli.envmap import latlong_pixel
    world = denv.directions @ np.asarray(rotation, np.float64).T
    px = latlong_pixel(world, denv.height, denv.width)
    col = np.clip(np.rint(px[:, 0]).astype(int), 0, denv.width - 1)
    row = np.clip(np.rint(px[:, 1]).astype(int), 0, denv.height - 1)
    grid = denv.radiance.reshape(denv.height, denv.width, 3)
    return grid[row, col].reshape(-1)


def wrist_rotations(hand, frame: int) -> list[np.ndarray]:
    """World rotation [3, 3] of each hand's root joint at ``frame``."""
    from scipy.spatial.transform import Rotation
    out = []
    for inst in hand.hands:
        local = Rotation.from_rotvec(np.asarray(inst.poses[frame][0], np.float64)).as_matrix()
        out.append(np.asarray(inst.root, np.float64)[:3, :3] @ local)
    return out


# ---------------------------------------------------------------- pseudo ground truth


class TeacherTargets:
    """The teacher's per-direction textures per (pose, camera), cached (see module doc).

    Args:
        model: the teacher (eval mode).  config: its TeacherConfig.
        data: CaptureData at the teacher's texture size.
        grid: a DiscreteEnv whose directions/solid angles define the 16×32 grid.
        cache_dir: folder for spilled textures (None: recompute beyond the budget); a
            damaged entry is a miss (see :meth:`textures`).
        budget_mb: memory kept.  device: torch device.  mean_texture: GGX teachers' T̄.
        chunk: directions per teacher pass.
        log: callable(str) for the one note about damaged cache entries (default: a line
            on stderr; the distill job passes the command's log, silent under ``-q``).
    """

    def __init__(self, model, config, data: CaptureData, grid, cache_dir: str | None = None,
                 budget_mb: int = 2048, device="cpu", mean_texture=None, chunk: int = 64,
                 identity: str = "", log=None):
        self.model = model
        self.log = log if log is not None else _stderr_note
        self.identity = identity
        self.config = config
        self.data = data
        self.directions = np.asarray(grid.directions, np.float64)
        self.solid_angle = np.asarray(grid.solid_angle, np.float64)
        self.cache_dir = cache_dir
        self.budget = int(budget_mb) * 2 ** 20
        self.device = device
        self.mean_texture = mean_texture
        self.chunk = chunk
        self._memory = OrderedDict()
        self._bytes = 0
        self._verified = {}
        self.computed = 0
        self.repaired = 0

    def _key(self, pose: int, camera: str, held_out: bool) -> str:
        text = f"{self.identity}|{self.data.key}|{held_out}|{pose}|{camera}|" \
               f"{self.config.to_json()}|{self.directions.tobytes().hex()[:64]}"
        return hashlib.sha256(text.encode()).hexdigest()[:24]

    def textures(self, pose: int, camera: str, held_out: bool = False) -> np.ndarray:
        """[H_hands, M, 3, N, N] float32 per-direction textures C_m (sr⁻¹).

        A ``--cache`` entry (``KEY.npy``) is used only when it is what this teacher
        computes there: a plain float32 ``.npy`` (never a pickle) of that shape, the
        file as long as its header says, every value finite.  Anything else is a miss:
        it is recomputed and rewritten, and the first such entry of a run is named once
        on stderr (``log``).  Entries are written atomically (a temporary file in the
        folder, renamed; removed on errors and Ctrl-C/SIGTERM/SIGHUP)."""
        key = self._key(pose, camera, held_out)
        if key in self._memory:
            self._memory.move_to_end(key)
            return self._memory[key]
        path = None if self.cache_dir is None else os.path.join(self.cache_dir, key + ".npy")
        damaged = False
        if path is not None and os.path.lexists(path):
            cached, why = self._read_cached(path, key, held_out)
            if cached is not None:
                return cached
            damaged = True
            self._note_damaged(path, why)
        value = self._compute(pose, camera, held_out)
        fits = value.nbytes + self._bytes <= self.budget
        if fits:
            self._memory[key] = value
            self._bytes += value.nbytes
        if path is not None and (damaged or not fits):
            self._write_cached(path, value)
        return value

    def _expected_shape(self, held_out: bool) -> tuple:
        hand = self.data.eval_hand if held_out and self.data.eval_hand is not None \
            else self.data.hand
        n = int(self.config.tex_res)
        return (len(hand.hands), len(self.directions), 3, n, n)

    def _read_cached(self, path: str, key: str, held_out: bool):
        """(memory-mapped array, None) of a valid cache entry, else (None, why)."""
        from numpy.lib import format as npy
        expected = self._expected_shape(held_out)
        try:
            stat = os.stat(path)
            if not os.path.isfile(path):
                return None, "not a file"
            with open(path, "rb") as f:
                version = npy.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = npy.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = npy.read_array_header_2_0(f)
                else:
                    return None, f"unknown .npy version {version}"
                offset = f.tell()
        except (OSError, ValueError, EOFError, SyntaxError) as exc:
            return None, f"not a .npy array: {(str(exc).splitlines() or ['?'])[0][:80]}"
        if dtype != np.dtype("<f4") or fortran:
            return None, f"holds {dtype} data, expected float32"
        if tuple(shape) != expected:
            return None, f"shape {tuple(shape)}, this teacher's is {expected}"[:160]
        if stat.st_size != offset + 4 * int(np.prod(expected)):
            return None, "truncated or padded"
        try:
            array = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            return None, f"unreadable: {(str(exc).splitlines() or ['?'])[0][:80]}"
        stamp = (stat.st_size, stat.st_mtime_ns, stat.st_ino)
        if self._verified.get(key) != stamp:
            flat = array.reshape(-1)
            step = 1 << 22
            for start in range(0, flat.size, step):
                if not np.isfinite(flat[start:start + step]).all():
                    return None, "holds NaN/Inf"
            self._verified[key] = stamp
        return array, None

    def _note_damaged(self, path: str, why: str) -> None:
        self.repaired += 1
        if self.repaired == 1 and self.log is not None:
            self.log(f"note: --cache entry {why}: recomputing and rewriting it (and any other "
                     f"damaged entry) ({path})")

    def _write_cached(self, path: str, value: np.ndarray) -> None:
        from relight_cli.fileio import atomic_path, outside_transaction
        os.makedirs(self.cache_dir, exist_ok=True)
        with outside_transaction(), atomic_path(path, suffix=".npy") as tmp:
            with open(tmp, "wb") as f:
                np.save(f, np.ascontiguousarray(value, np.float32), allow_pickle=False)
        self._verified.pop(os.path.basename(path)[:-4], None)

    @torch.no_grad()
    def _compute(self, pose: int, camera_name: str, held_out: bool) -> np.ndarray:
        cfg = self.config
        texels = self.data.texels(pose, held_out)
        camera = self.data._cameras[camera_name]
        poses = pose_vector(self.data.poses(pose, held_out)).to(self.device)
        mean = None
        if self.mean_texture is not None:
            mean = self.mean_texture.expand(texels.n_hands, -1, -1, -1)
        ones = np.ones((len(self.directions), 3), np.float32)
        out = []
        for k in range(texels.n_hands):
            lights = texels.directional_lights(k, self.directions, visibility=cfg.visibility)
            view = texels.local_view(k, camera.center)
            parts = []
            for start in range(0, len(self.directions), self.chunk):
                sl = slice(start, start + self.chunk)
                from .geometry import LightInputs
                sub = LightInputs(lights.local_light[sl], lights.visibility[sl],
                                  lights.falloff[sl])
                x, _ = assemble_inputs(texels, k, sub, view, ones[sl], cfg.visibility, "analytic")
                inputs = torch.from_numpy(x).to(self.device)
                hand_of = torch.full((len(x),), k, dtype=torch.long, device=self.device)
                parts.append(self.model(inputs, poses, hand_of, mean).cpu().numpy())
            out.append(np.concatenate(parts))
        self.computed += 1
        return np.stack(out).astype(np.float32)

    def texture(self, pose: int, camera: str, denv, held_out: bool = False) -> list:
        """Per hand target textures Σ_m b_m C_m [3, N, N] (torch) under ``denv``."""
        if not np.array_equal(denv.directions, self.directions):
            raise ValueError("env maps must use the pseudo ground truth's direction grid")
        b = torch.from_numpy((denv.radiance * self.solid_angle[:, None]).astype(np.float32))
        tex = self.textures(pose, camera, held_out)
        return [torch.einsum("mc,mcxy->cxy", b, torch.from_numpy(np.array(t)))
                for t in tex]

    def image(self, pose: int, camera: str, denv, held_out: bool = False) -> torch.Tensor:
        """[H, W, 3] the teacher's render of (pose, camera) under ``denv``."""
        gb = self.data.gbuffer(pose, self.data._cameras[camera], held_out)
        return composite(self.texture(pose, camera, denv, held_out), gb)


def _stderr_note(message: str) -> None:
    """A note on stderr, one line (the default ``log`` of Python use: a command passes
    its own, silent under its -q)."""
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


# ---------------------------------------------------------------- student inputs


class StudentFeatures:
    """bake-features' texel maps of a capture's poses (coarse proxy), cached per pose.

    Channels per hand: diffuse (3) then phong<α> (3 each) when ``specular``.
    """

    def __init__(self, config, cache: int = 16, env_res=None):
        from relight_cli import features as FE
        self.config = config
        #: (H, W) of the directions visibility is traced for (default: the training grid)
        self.env_res = tuple(config.env_res if env_res is None else env_res)
        self.settings = FE.FeatureSettings(shininess=tuple(float(a) for a in config.shininess),
                                           specular="phong" if config.specular else "none",
                                           visibility=config.visibility)
        self._poses = LRU(cache)
        self._rasters = {}
        self.names = ["diffuse"] + ([FE.phong_name(a) for a in self.settings.phong]
                                    if config.specular else [])

    @property
    def channels(self) -> int:
        return 3 * len(self.names)

    def pose(self, hand, frame: int, key=None, posed=None):
        from relight_cli.bake import PoseFeatures
        n = self.config.tex_res
        return self._poses.get_or(key if key is not None else (id(hand), frame), lambda: PoseFeatures(
            hand, frame, self.settings, self.env_res, (n, n), "coarse",
            self._rasters, posed=posed))

    def maps(self, pose_features, denv, eye) -> np.ndarray:
        """[H_hands, C, N, N] float32 features under ``denv`` seen from ``eye``."""
        _, texel = pose_features.bake([denv], np.asarray(eye, np.float64))
        out = []
        for maps in texel[0]:
            out.append(np.concatenate([np.transpose(maps[name], (2, 0, 1)) for name in self.names]))
        return np.stack(out).astype(np.float32)


def student_forward(net, config, feats: np.ndarray, poses: np.ndarray, denv, wrists, device,
                    return_raw: bool = False):
    """Normalized forward pass: (per-hand textures [3, N, N] in radiance, raw, scale s).

    ``feats`` None: DRAM, whose only light input is its env code (no texel features are
    baked for it: it never reads them)."""
    s = env_scale(denv)
    if feats is None:
        n = int(config.tex_res)
        x = torch.zeros((len(wrists), 0, n, n), device=device)
    else:
        x = torch.from_numpy(feats / s).to(device)
    p = pose_vector(poses).to(device)
    code = None
    if not reads_texel_features(config):
        code = torch.from_numpy(np.stack([np.log1p(wrist_env(denv, r) / s) for r in wrists])
                                .astype(np.float32)).to(device)
    tex, raw = net(x, p, code, return_raw=True)
    textures = [tex[k] * s for k in range(tex.shape[0])]
    return (textures, raw, s) if return_raw else textures


#: most poses whose student features (visibility) a StudentTask keeps
FEATURE_POSES = 1024


class StudentTask:
    """What :func:`relight_cli.neural.train.fit` needs to distill a student.

    Args:
        data: the capture (CaptureData at the teacher's texture size).
        config: StudentConfig.  targets: TeacherTargets.
        envs: list of DiscreteEnvs (the env-res grid); train_idx / eval_idx: the split.
        env_names: names (for the record).  vgg: optional VGG loss.
        teacher_digest: SHA-256 of the teacher checkpoint (stored in the student).
    """

    kind = "student"
    desc = "distill"

    def __init__(self, data: CaptureData, config, targets: TeacherTargets, envs: list,
                 train_idx: list, eval_idx: list, env_names: list, vgg=None,
                 teacher_digest: str = ""):
        self.data = data
        self.config = config
        self.targets = targets
        self.envs = envs
        self.train_idx = train_idx
        self.eval_idx = eval_idx
        self.env_names = env_names
        self.vgg = vgg
        self.teacher_digest = teacher_digest
        frames = data.train_frames + data.train_fully_lit_frames    # no held-out segment
        poses = sorted({f.pose for f in frames})
        # every pose's features kept (≈ 1 MB each at 8×16 directions, its traced
        # visibility), and 16 more for the evaluation hand's: with a 16-pose cache a
        # 48-pose capture re-traced visibility on two samples in three, 26 % of a converged
        # student's time (py-spy)
        self.features = StudentFeatures(config, cache=min(
            FEATURE_POSES, len(poses) + len({f.pose for f in data.heldout_frames}) + 16))
        #: features on other grids (``render_env_res``: held-out scoring), by (H, W)
        self._grid_features = {self.features.env_res: self.features}
        self._heldout_poses = len({f.pose for f in data.heldout_frames})
        cams = [c.name for c in data.capture.cameras]
        self.items = [(p, c) for p in poses for c in cams]
        self.model_name = config.student
        self.capture_key = data.key
        self.pose_dim = data.pose_dim
        self._cam_index = {c: i for i, c in enumerate(cams)}

    def check(self):
        if not self.items:
            raise DataError("no training poses in the capture", self.data.index_path)

    def build(self, device, resume=None):
        net = build_student(self.config, self.features.channels, self.pose_dim)
        if (resume is None and getattr(self.config, "head_init", "grey") == "lsq"
                and device != torch.device("meta")):
            fit_linear_head(self, net)
        return net.to(device)

    def restore(self, resume, device):
        pass

    def env_for(self, step: int, item, rng=None) -> object:
        """The training env map of ``item`` at ``step`` (seeded by both), or drawn from
        ``rng`` when given."""
        if rng is None:
            rng = np.random.default_rng([int(self.config.seed), int(step), int(item[0]),
                                         self._cam_index[item[1]]])
        if getattr(self.config, "env_augment", "paper") == "mix":
            return mix_env([self.envs[i] for i in self.train_idx], rng, self.config.rotations)
        env = self.envs[self.train_idx[int(rng.integers(len(self.train_idx)))]]
        if self.config.rotations:
            env = rotate_env(env, int(rng.integers(env.width - 1)))
        return env

    def render(self, net, pose: int, camera: str, denv, device, held_out: bool = False,
               return_raw: bool = False, clip: bool = True):
        """The student's image of (pose, camera) under ``denv``; ``clip`` False: the
        linear head's texture unclipped (its training loss, see
        :class:`~relight_cli.neural.student.LinearHeadStudent`)."""
        textures, raw, s = self.textures(net, pose, camera, denv, device, held_out, clip)
        image = composite(textures, self.data.gbuffer(pose, self.data._cameras[camera],
                                                      held_out))
        return (image, raw, s) if return_raw else image

    def textures(self, net, pose: int, camera: str, denv, device, held_out: bool = False,
                 clip: bool = True):
        """(per-hand textures [3, N, N], raw head output [H, 3, N, N], env scale s) of the
        student at (pose, camera) under ``denv``; ``clip`` as :meth:`render`."""
        hand = self.data.eval_hand if held_out else self.data.hand
        key = (held_out, pose)
        features = self.features_on((denv.height, denv.width))
        cam = self.data._cameras[camera]
        feats = None                 # DRAM: no texel features (nothing traced per pose)
        if reads_texel_features(self.config):
            feats = features.maps(features.pose(hand, pose, key=key), denv, cam.center)
        wrists = wrist_rotations(hand, pose)
        textures, raw, s = student_forward(net, self.config, feats, hand_poses(hand, pose), denv,
                                           wrists, device, return_raw=True)
        if not clip:
            textures = [raw[k] * s for k in range(raw.shape[0])]
        return textures, raw, s

    def chart_mask(self, device) -> torch.Tensor:
        """[1, 1, N, N] bool: the texels inside the UV charts at the student's N (the UV
        layout is the same for every pose and hand)."""
        if getattr(self, "_chart_mask", None) is None:
            from relight_cli.uvraster import rasterize_uv
            mesh = self.data.hand.mesh("fine")
            inside = rasterize_uv(mesh.uv, mesh.faces_uv, int(self.config.tex_res)).inside
            self._chart_mask = torch.from_numpy(np.ascontiguousarray(inside))[None, None]
        return self._chart_mask.to(device)

    def _texture_mse(self, net, pose, camera, denv, device, clip):
        """``loss_space: texture``: (the masked MSE between the student's and the
        teacher's textures, both ÷ s, over the chart texels of every hand; the student's
        textures, raw head output and s as :meth:`textures` gives them)."""
        textures, raw, s = self.textures(net, pose, camera, denv, device, False, clip)
        pred = torch.stack(textures)
        target = at_student_res(torch.stack(self.targets.texture(pose, camera, denv))
                                .to(device), pred.shape[-1])
        mask = self.chart_mask(device).expand(pred.shape[0], 3, -1, -1)
        mse = ((pred - target) / s)[mask].pow(2).mean()
        return mse, textures, raw, s

    def features_on(self, grid) -> StudentFeatures:
        """The student's features with visibility traced on the env grid ``grid`` (H, W):
        the training grid's, or (``render_env_res``) another's, kept for the held-out
        poses.  DRAM's light code is its training grid's: another grid is a ValueError."""
        grid = tuple(int(v) for v in grid)
        if grid not in self._grid_features:
            check_render_grid(self.config, grid)
            self._grid_features[grid] = StudentFeatures(self.config,
                                                        cache=self._heldout_poses + 16,
                                                        env_res=grid)
        return self._grid_features[grid]

    def loss(self, net, item, step, device):
        pose, camera = item
        denv = self.env_for(step, item)
        cfg = self.config
        clip = getattr(cfg, "head", "eq11") != "linear"
        perceptual_on = self.vgg is not None and cfg.lambda_vgg > 0
        texture_space = getattr(cfg, "loss_space", "image") == "texture"
        if texture_space:
            mse, textures, raw, s = self._texture_mse(net, pose, camera, denv, device, clip)
        if not texture_space or perceptual_on:         # the image and its target
            gb = self.data.gbuffer(pose, self.data._cameras[camera])
            mask = torch.from_numpy(gb.mask > 0).to(device)
            if texture_space:
                image = composite(textures, gb)
            else:
                image, raw, s = self.render(net, pose, camera, denv, device, return_raw=True,
                                            clip=clip)
            target = self.targets.image(pose, camera, denv).to(device)
        if not texture_space:
            mse = masked_mse(image / s, target / s, mask)
        total = cfg.lambda_mse * mse
        parts = {"mse": float(mse.detach())}
        if perceptual_on:
            perceptual = self.vgg(image / s, target / s, mask)
            total = total + cfg.lambda_vgg * perceptual
            parts["vgg"] = float(perceptual.detach())
        if cfg.lambda_neg > 0:
            gamma = neg_weight(step, cfg.neg_eta, cfg.neg_start, cfg.neg_schedule)
            region = torch.ones_like(raw[:, :1])
            neg = negativity(raw, region)
            total = total + cfg.lambda_neg * gamma * neg
            parts["neg"] = float(neg.detach())
        return total, parts

    def evaluate(self, model, device) -> dict:
        return evaluate_student(self, model, device)

    def extra(self) -> dict:
        import json

        from .geometry import uv_layout_digest
        return {"uv_layout": uv_layout_digest(self.data.hand.mesh("fine")),
                "teacher_sha256": self.teacher_digest,
                "envs": json.dumps({"train": [self.env_names[i] for i in self.train_idx],
                                    "eval": [self.env_names[i] for i in self.eval_idx]})}


def at_student_res(textures: torch.Tensor, n: int) -> torch.Tensor:
    """Teacher textures [..., 3, M, M] at the student's N×N: unchanged when M = N, else
    resampled (bilinear, antialiased) — the one resampling of the teacher's textures to
    the student's texels, shared by the texture loss and the least-squares start, so a
    teacher of another ``tex_res`` is compared the same way in both."""
    if tuple(textures.shape[-2:]) == (n, n):
        return textures
    import torch.nn.functional as F
    lead = textures.shape[:-3]
    flat = textures.reshape(-1, *textures.shape[-3:])
    out = F.interpolate(flat, size=(n, n), mode="bilinear", align_corners=False,
                        antialias=True)
    return out.reshape(*lead, *out.shape[-3:])


#: ``head_init: lsq``: passes over the training (pose, camera) pairs, each under its own
#: drawn training env map, and the ridge weight (× the mean diagonal of a texel's normal
#: matrix) that pulls texels with little or no data towards the grey start
LSQ_PASSES, LSQ_RIDGE = 2, 1e-4


@torch.no_grad()
def fit_linear_head(task: StudentTask, net) -> int:
    """``head_init: lsq``: the linear head's per-texel weights set to the least-squares fit
    of the teacher's textures by the student's own features (before any SGD step).

    With the pose-dependent part at zero (its last conv starts at zero), the linear head
    is C = Σ_k W_k ⊙ F_k with W the per-texel weights alone: per texel and colour channel
    a K-unknown linear least-squares problem (K feature maps) over every training sample,
    solved in closed form from its normal equations,
    W = (Σ F Fᵀ + λ I)⁻¹ (Σ F T + λ W₀), λ = ``LSQ_RIDGE`` × the mean diagonal of Σ F Fᵀ
    over texels, W₀ the grey start (so a texel no camera's features reach keeps it).
    Samples: ``LSQ_PASSES`` passes over the training (pose, camera) pairs, each under an
    env map drawn as training draws them (seeded by the run's seed and the pass), features
    and target both divided by the map's mean radiance as the loss divides them; the
    texture is the teacher's (every texel, seen from the pair's camera), at the student's
    N as the texture loss takes it (:func:`at_student_res`).  The ReLU of the
    head is not part of the fit (the features and the fitted weights are mostly ≥ 0).
    Returns the number of (sample, hand) textures fitted."""
    cfg = task.config
    n, k = int(cfg.tex_res), net.maps
    start = net.weight_bias.detach().double().reshape(k, 3 * n * n).T.numpy()
    gram = np.zeros((3 * n * n, k, k))
    rhs = np.zeros((3 * n * n, k))
    samples = 0
    for npass in range(LSQ_PASSES):
        rng = np.random.default_rng([int(cfg.seed), 17, npass])
        for item in task.items:
            pose, camera = item
            denv = task.env_for(0, item, rng)
            s = env_scale(denv)
            pf = task.features.pose(task.data.hand, pose, key=(False, pose))
            feats = task.features.maps(pf, denv, task.data._cameras[camera].center)
            for hand_feats, target in zip(feats, task.targets.texture(pose, camera, denv)):
                f = (hand_feats.astype(np.float64) / s).reshape(k, 3 * n * n).T
                t = at_student_res(target, n).double().numpy().reshape(-1) / s
                gram += f[:, :, None] * f[:, None, :]
                rhs += f * t[:, None]
                samples += 1
    ridge = LSQ_RIDGE * float(np.trace(gram, axis1=1, axis2=2).mean()) / k
    ridge = max(ridge, 1e-12)
    w = np.linalg.solve(gram + ridge * np.eye(k), (rhs + ridge * start)[..., None])[..., 0]
    net.weight_bias.copy_(torch.from_numpy(w.T.reshape(1, 3 * k, n, n).astype(np.float32)))
    return samples


def render_grid(config) -> tuple:
    """(H, W) env grid a student renders on after training: ``render_env_res``, else its
    training grid ``env_res``."""
    return tuple(config.render_env_res or config.env_res)


def reads_texel_features(config) -> bool:
    """Whether the student reads bake-features' texel maps (RelightableHands' student);
    DRAM (App. A.3) reads a light code of the env map instead, so none are traced."""
    return config.student != "dram"


def check_render_grid(config, grid) -> None:
    """The one check of the grid (H, W) a student renders on: the texel-aligned student
    renders on any grid; DRAM's light code is its training grid's (App. A.3), so another
    grid is a ValueError."""
    if not reads_texel_features(config) and tuple(int(v) for v in grid) != tuple(config.env_res):
        from relight_cli.envmap import EnvGrid
        raise ValueError(f"DRAM renders on its training grid: the DRAM student was trained on "
                         f"a {EnvGrid(*config.env_res)} (WxH) env grid, its light code's; "
                         f"--env-res must match")


def hand_poses(hand, frame: int) -> np.ndarray:
    return np.stack([inst.poses[frame] for inst in hand.hands])


def _metrics(pred, gt, mask):
    from .train import _metrics as image_metrics
    return image_metrics(pred, gt, mask)


def _student_texels(task, pose: int):
    """The held-out pose's texel G-buffer at the student's N (the capture data's own
    when the teacher's N is the same), for the ceiling of ``vs_ground_truth``."""
    data, n = task.data, int(task.config.tex_res)
    if n == data.tex_res:
        return data.texels(pose, held_out=True)
    cache = task.__dict__.setdefault("_ceiling_texels", {})
    if pose not in cache:
        from .geometry import PoseTexels
        cache[pose] = PoseTexels(data.meshes(pose, True), n, shadows=data.visibility)
    return cache[pose]


@torch.no_grad()
def evaluate_student(task: StudentTask, model, device) -> dict:
    """Held-out poses × evaluation env maps, scored against the teacher (``vs_teacher``,
    as the paper does) and the capture's ground-truth env renders (``vs_ground_truth``,
    its held-out poses under its own env maps; on a synthetic capture with ``ceiling`` and
    ``gap_to_ceiling``: the perfect texture at the student's N through the same
    compositing, :class:`~relight_cli.neural.evaluate.Ceiling`)."""
    model.eval()
    data, cfg = task.data, task.config
    out = {}
    rows = []
    envs = [task.envs[i] for i in (task.eval_idx or task.train_idx)]
    pairs = [(f.pose, cam) for f in data.heldout_frames for cam in f.images]
    combos = [(p, c, e) for p, c in pairs for e in range(len(envs))]
    pick = np.unique(np.linspace(0, len(combos) - 1, min(len(combos), cfg.val_samples))
                     .round().astype(int)) if combos else []
    for i in pick:
        pose, cam, e = combos[i]
        pred = task.render(model, pose, cam, envs[e], device).cpu().numpy()
        gt = task.targets.image(pose, cam, envs[e]).cpu().numpy()
        mask = data.gbuffer(pose, data._cameras[cam]).mask
        m = _metrics(pred, gt, mask)
        if m:
            rows.append(m)
    if rows:
        out["vs_teacher"] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        out["vs_teacher"]["samples"] = len(rows)
    splits = data.splits()
    if splits.get("env"):
        from relight_cli.envmap import discretize_env
        renders = splits["env"]
        pick = np.unique(np.linspace(0, len(renders) - 1, min(len(renders), cfg.val_samples))
                         .round().astype(int))
        from .scores import attach_ceiling
        from .ceiling import ceiling_of
        ceiling = ceiling_of(data)
        rows, best = [], []
        for i in pick:
            pose, env_name, camera, gt, mask = data.env_target(renders[i][1])
            denv = discretize_env(data.env_map(env_name), *render_grid(cfg))
            pred = task.render(model, pose, camera.name, denv, device, held_out=True)
            m = _metrics(pred.cpu().numpy(), gt, mask)
            if m:
                rows.append(m)
                if ceiling.available:   # the perfect texture at the student's N, same view
                    texels = _student_texels(task, pose)
                    best.append(ceiling.score(renders[i], [texels] * texels.n_hands,
                                              data.gbuffer(pose, camera, held_out=True), gt,
                                              mask))
        if rows:
            scores = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
            scores["samples"] = len(rows)
            scores["env_res"] = list(render_grid(cfg))
            out["vs_ground_truth"] = attach_ceiling(scores, best)
    model.train()
    return out


