"""Per-frame cost of relighting a real hand motion, one process per sequence (issue 25).

1. Fits the Leap Motion recordings in ``../shared/data/hands/leap/`` (``grab``, ``pinch``,
   ``wave``: one right hand each) once with ``relight fit-geometry --keypoints``, every
   frame; the two-hand scene is the ``--recording``'s fit plus its mirror image beside it
   (``relight_cli.hand.scene.two_hands``, what ``fit-geometry --two-hands`` adds: the
   recordings hold one hand only).
2. Builds the learned models through the Python API at the papers' widths — untrained
   (random initialization): their numbers are timings only, their images mean nothing —
   writes them with ``formats.checkpoint.make_checkpoint``/``write_checkpoint`` and loads
   them back with the loaders ``relight relight`` uses (``read_checkpoint``, then
   ``neural.checkpoints.student_model`` / ``neural.evaluate.load_hand_model``): the student at
   ``STUDENT_PRESETS["paper"]`` (128² features, decoder 256…32), URHand's linear model at
   its ``paper`` widths on a ``--linear-tex`` texture (paper 1024²), the OLAT teacher at
   its ``paper`` widths on a ``--teacher-tex`` texture (paper 1024²).  The physical
   renderer needs no model.  One fixed 256×256 camera per scene
   (``hand.scene.preview_camera`` framing five frames spread over the selection).
3. Runs each job of ``relight_cli.jobs.relight_hand`` (``physical``, ``student``,
   ``learned``) over the recording's frames in this one process — up to ``--frames N``,
   stopping early once a job has spent ``--budget`` seconds (at least 2 frames) — and
   reports per model and scene the first frame (warm-up) apart, and the median and p95
   ms per frame of each stage the job reports, the wall time per frame and frames/s;
   the stages are mapped onto RelightableHands App. C's split (pose/joints, visibility,
   UV sampling/transport, decoder, compositing).
4. Measures the machine's limits in the same run: fp32 GEMM and dense 3×3 conv GFLOP/s,
   memory bandwidth, raw embree rays/s on a sphere (``_common.machine_limits``) and on
   the very rays the student's feature bake traced for one frame.
5. Runs ``relight relight ... --frames 0:K`` once against K single-frame calls
   (``--frame k``) as subprocesses for the linear model and the physical renderer: wall
   times, the per-call start-up cost they imply, and an extrapolation to 300 frames.

torch runs on ``--threads`` (default 1, passed to the CLI processes as OMP_NUM_THREADS: on
the shared 2-core machine a second torch thread waits for cores other jobs hold; a
thread check re-times the student on every core).

Writes sequence.{md,json,png} under --out (default benchmarks/out); ``--report`` rewrites
the Markdown and the plot from the JSON there.  ``--quick``: the
first 5 frames of the recording, tiny widths and textures, a 96×96 view, K = 2 (a smoke
run, not a measurement).  Run:
    .venv/bin/python benchmarks/bench_sequence.py [--quick] [--frames N] [--budget S] [--k K] [--out DIR]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

LEAP = B.ROOT.parent / "shared" / "data" / "hands" / "leap"
RECORDINGS = ("grab", "pinch", "wave")
HDRI = B.ROOT.parent / "shared" / "data" / "envmaps" / "polyhaven" / "studio_small_03_1k.hdr"
MODELS = ("physical", "student", "linear", "teacher")
#: RelightableHands App. C's split of a student frame, and its V100 numbers (ms; no
#: compositing figure; 21 ms a frame for one hand, 32 for two).
APPC = ("pose/joints", "visibility", "UV sampling/transport", "decoder", "compositing",
        "untimed")
PAPER_MS = {"pose/joints": 0.3, "visibility": 2.7, "UV sampling/transport": 1.5,
            "decoder": 15.8}
PAPER_TOTAL = {1: 21.0, 2: 32.0}


# ------------------------------------------------------------------ inputs


def relight_exe() -> list:
    """The ``relight`` console script of this interpreter's environment (what a user runs)."""
    exe = Path(sys.executable).with_name("relight")
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-c", "import sys; from relight_cli.cli import main; sys.exit(main())"]


def fit_recordings(work: Path, names, quick: bool) -> dict:
    """One hand.npz per Leap recording (``relight fit-geometry --keypoints``, every frame;
    quick: the first 5): {name: {path, frames, fit seconds, MPJPE mm, command}}."""
    out = {}
    for name in names:
        src = LEAP / f"{name}.json"
        args = ["fit-geometry", "--keypoints", str(src), "-o", str(work / f"{name}.npz"),
                "--report", str(work / f"{name}_fit.json"), "-q"]
        if quick:
            args[3:3] = ["--frames", "0:5"]
        t0 = time.perf_counter()
        subprocess.run(relight_exe() + args, check=True)
        seconds = time.perf_counter() - t0
        report = json.loads((work / f"{name}_fit.json").read_text())
        shown = ["relight", *args]
        shown[shown.index(str(src))] = f"../shared/data/hands/leap/{name}.json"
        frames = report.get("output_frames", report["fitted_frames"])
        out[name] = {"path": str(work / f"{name}.npz"),
                     "frames": len(frames) if isinstance(frames, list) else int(frames),
                     "fitted_frames": int(report["fitted_frames"]),
                     "mpjpe_mm": float(report["mpjpe_mm"]), "fit_seconds": seconds,
                     "command": " ".join(a if not a.startswith(str(work)) else
                                         Path(a).name for a in shown)}
    return out


def fixed_camera(hand, frames, size: int):
    """One camera framing the posed hands of five frames spread over ``frames``."""
    from relight_cli.bake import pose_scene
    from relight_cli.hand.scene import preview_camera
    picks = sorted({frames[int(round(i))] for i in np.linspace(0, len(frames) - 1, 5)})
    meshes = [m for f in picks for m in pose_scene(hand, f, "fine", "bench")]
    return preview_camera(meshes, size, size)


def build_models(work: Path, hand, wanted, quick: bool, linear_tex: int, teacher_tex: int):
    """Untrained models at the papers' widths (quick: tiny), written as checkpoints and
    loaded back as the CLI loads them: {kind: {path, loaded model, config, description}}."""
    import torch

    from relight_cli.formats.checkpoint import make_checkpoint, write_checkpoint
    from relight_cli.neural.checkpoints import read_checkpoint
    from relight_cli.neural import linear as L
    from relight_cli.neural.config import PRESETS, STUDENT_PRESETS, StudentConfig, \
        TeacherConfig, resolve_config
    from relight_cli.neural.evaluate import load_hand_model
    from relight_cli.neural.geometry import hand_records, uv_layout_digest
    from relight_cli.neural.models import build_model
    from relight_cli.neural.train import rng_state

    preset = "tiny" if quick else "paper"
    pose_dim = (hand.n_joints - 1) * 3
    layout = uv_layout_digest(hand.mesh("fine"))
    records = hand_records(hand)
    provenance = {"command": "benchmarks/bench_sequence.py",
                  "note": "untrained (random initialization): for timing only"}
    models = {}

    def save(kind, name, cfg, net, extra):
        path = work / f"{kind}.pt"
        write_checkpoint(str(path), make_checkpoint(
            kind, name, cfg.to_dict(), 0,
            {k: v.detach().clone() for k, v in net.state_dict().items()},
            torch.optim.Adam(net.parameters()).state_dict(), rng_state(), "bench_sequence",
            pose_dim, provenance, extra))
        return path, read_checkpoint(str(path), kind=kind)

    def size(net):
        return int(sum(p.numel() for p in net.parameters()))

    if "student" in wanted:
        from relight_cli.neural.checkpoints import student_model
        from relight_cli.neural.student import build_student
        cfg = resolve_config(preset, None, {}, presets=STUDENT_PRESETS, config_class=StudentConfig)
        channels = 3 * (1 + (len(cfg.shininess) if cfg.specular else 0))
        net = build_student(cfg, channels, pose_dim)
        t0 = time.perf_counter()
        path, ckpt = save("student", "student", cfg, net, {"uv_layout": layout})
        loaded, cfg = student_model(ckpt, "cpu")
        models["student"] = {
            "path": str(path), "net": loaded, "config": cfg, "parameters": size(loaded),
            "load_seconds": time.perf_counter() - t0,
            "describe": f"student, STUDENT_PRESETS[{preset!r}]: {cfg.tex_res}² texel features "
                        f"({channels} channels: diffuse + Phong {'/'.join(map(str, cfg.shininess))}), "
                        f"decoder {', '.join(map(str, cfg.decoder))}, J_s {'/'.join(map(str, cfg.pose_channels))}, "
                        f"env {cfg.env_res[1]}×{cfg.env_res[0]}"}
    if "linear" in wanted:
        overrides = {"lambda_gan": 0.0}          # the discriminator is training-only
        if not quick:
            overrides["tex_res"] = linear_tex
        cfg = L.resolve_config(preset, None, overrides)
        net = L.URHandModel(cfg, pose_dim)
        mean = torch.full((1, 3, cfg.tex_res, cfg.tex_res), 0.15)
        t0 = time.perf_counter()
        path, ckpt = save("linear", "linear", cfg, net,
                          {"uv_layout": layout, "hands": records, "mean_texture": mean})
        loaded = load_hand_model(ckpt, "cpu", name=str(path))
        models["linear"] = {
            "path": str(path), "model": loaded, "config": cfg, "parameters": size(net),
            "load_seconds": time.perf_counter() - t0,
            "describe": f"URHand linear, PRESETS[{preset!r}] widths (F_G {'/'.join(map(str, cfg.encoder))}, "
                        f"light path {', '.join(map(str, cfg.light_decoder))}, {cfg.light_levels} "
                        f"levels) on a {cfg.tex_res}² texture (paper 1024²), λ_GAN 0 (training only)"}
    if "teacher" in wanted:
        overrides = {} if quick else {"tex_res": teacher_tex}
        cfg = resolve_config(preset, None, overrides, presets=PRESETS, config_class=TeacherConfig)
        net = build_model(cfg, pose_dim)
        t0 = time.perf_counter()
        path, ckpt = save("teacher", cfg.model, cfg, net, {"uv_layout": layout, "hands": records})
        loaded = load_hand_model(ckpt, "cpu", name=str(path))
        models["teacher"] = {
            "path": str(path), "model": loaded, "config": cfg, "parameters": size(net),
            "load_seconds": time.perf_counter() - t0,
            "describe": f"OLAT teacher, PRESETS[{preset!r}] widths (encoder "
                        f"{'/'.join(map(str, cfg.encoder))}, decoder {'/'.join(map(str, cfg.decoder))}) "
                        f"on a {cfg.tex_res}² texture (paper 1024²): one U-Net pass per lit env "
                        f"direction and hand"}
    if "physical" in wanted:
        models["physical"] = {"describe": physical_describe(quick)}
    return models


def physical_describe(quick: bool) -> str:
    h, w = env_grid(quick)
    return (f"physically based (Lambert + GGX + SSS, embree shadows): {64 if quick else 256}² "
            f"lighting maps, aa 2, env {w}×{h} " + ("(quick: smaller than the CLI's defaults)"
                                                   if quick else "(the CLI's defaults)"))


# ------------------------------------------------------------------ timing probes


class Probes:
    """Time functions a job calls, without touching the job: each ``(owner, attribute,
    bucket)`` is wrapped for the duration (missing ones are skipped and listed), and
    :meth:`take` returns and clears the seconds per bucket (per frame)."""

    def __init__(self, targets):
        self.targets = targets
        self.seconds = {}
        self.saved = []
        self.missing = []

    def __enter__(self):
        for owner, name, bucket in self.targets:
            original = getattr(owner, name, None)
            if original is None:
                self.missing.append(f"{getattr(owner, '__name__', owner)}.{name}")
                continue

            def wrapper(*a, _f=original, _b=bucket, **k):
                t0 = time.perf_counter()
                try:
                    return _f(*a, **k)
                finally:
                    self.seconds[_b] = self.seconds.get(_b, 0.0) + time.perf_counter() - t0

            setattr(owner, name, wrapper)
            self.saved.append((owner, name, original))
        return self

    def take(self) -> dict:
        out, self.seconds = self.seconds, {}
        return out

    def __exit__(self, *exc):
        for owner, name, original in reversed(self.saved):
            setattr(owner, name, original)
        return False


class BakeCapture:
    """Keep the PoseFeatures of each frame the student's job bakes (its per-stage
    thread-seconds, its rays): wraps ``StudentFeatures.maps`` while active."""

    def __init__(self):
        self.last = None
        self._saved = None

    def __enter__(self):
        from relight_cli.neural import distill as D
        cls = getattr(D, "StudentFeatures", None)
        if cls is not None:
            original = cls.maps

            def maps(obj, pose_features, *a, **k):
                out = original(obj, pose_features, *a, **k)
                self.last = pose_features
                return out

            cls.maps = maps
            self._saved = (cls, original)
        return self

    def __exit__(self, *exc):
        if self._saved:
            self._saved[0].maps = self._saved[1]
        return False


def probe_targets(kind: str) -> list:
    """What each job's stages hide: the view's G-buffer cast (inside the learned jobs'
    *geometry*; the jobs import ``render_gbuffer`` when they start, so the module's
    attribute is the one they call), the linear model's shading features and the
    learned jobs' compositing (inside *network* / outside every stage), the physical
    renderer's env visibility rays (inside *direct* and *shade*)."""
    from relight_cli.visibility import VisibilityCache
    from relight_cli.neural import evaluate as EV
    from relight_cli.render import gbuffer as G
    if kind == "physical":
        return [(VisibilityCache, "require", "trace")]
    targets = [(G, "render_gbuffer", "gbuffer")]
    if kind == "linear":
        from relight_cli.neural import linear as L
        targets += [(L, n, "shading features") for n in ("refined_normals", "map_to_texels",
                                                         "shading_features", "texels_to_map")]
    if kind in ("linear", "teacher"):
        targets.append((EV, "composite", "composite"))
    return targets


# ------------------------------------------------------------------ jobs


def make_job(kind: str, hand, cam, models: dict, envmap, quick: bool):
    """(frames → generator of FrameRender, preparation seconds): what the CLI prepares
    once per sequence (materials, the discretized env map) is prepared here.  Env grid:
    the CLI's default 32×16 (quick: 16×8) except the student's own."""
    from relight_cli.envmap import discretize_env
    from relight_cli.jobs import relight_hand as J

    view_of = lambda frame, meshes: cam  # noqa: E731  a fixed camera
    bg = (0.0, 0.0, 0.0)
    t0 = time.perf_counter()
    if kind == "physical":
        from relight_cli.render import appearance as A
        from relight_cli.render.shading import RenderSettings
        tex = 64 if quick else 256
        materials = A.hand_materials(hand, "fine", max(tex, 256), 0, None, None)
        settings = RenderSettings(tex_res=tex, aa=2, shadows=True, specular=True, sss=True,
                                  sss_scale=1.0, env_res=env_grid(quick), bounce=False)
        prep = time.perf_counter() - t0
        return (lambda frames: J.physical(hand, frames, view_of, materials, settings, None,
                                          envmap, bg, "fine", (), "bench")), prep
    if kind == "student":
        m = models["student"]
        denv = discretize_env(envmap, *m["config"].env_res)
        prep = time.perf_counter() - t0
        return (lambda frames: J.student(hand, frames, view_of, m["net"], m["config"], denv, 2,
                                         bg, "cpu", "bench", "float32")), prep
    m = models[kind]
    per_hand = [m["model"]] * len(hand.hands)
    denv = discretize_env(envmap, *env_grid(quick))
    prep = time.perf_counter() - t0
    return (lambda frames: J.learned(hand, frames, view_of, per_hand, 2, None, denv, bg, "cpu",
                                     "bench")), prep


def env_grid(quick: bool) -> tuple:
    """(H, W) of the env directions: the CLI's default --env-res 32x16; quick 16x8."""
    return (8, 16) if quick else (16, 32)


def run_job(kind: str, factory, frames: list, budget: float) -> dict:
    """Render ``frames`` in one generator, timing each ``next``: per frame its wall
    seconds, the job's stage seconds, the probes' seconds, coverage and passes; stops
    early when the next frame would take the job past ``budget`` seconds (≥ 2 frames)."""
    rows = []
    capture = BakeCapture() if kind == "student" else None
    bakes = []
    with Probes(probe_targets(kind)) as probes, (capture or _Null()):
        gen = factory(frames)
        start = time.perf_counter()
        while True:
            t0 = time.perf_counter()
            try:
                r = next(gen)
            except StopIteration:
                break
            wall = time.perf_counter() - t0
            row = {"frame": int(r.frame), "wall": wall, "stages": dict(r.seconds),
                   "probes": probes.take(), "passes": int(r.passes),
                   "coverage": float(np.mean(r.channels["A"]))}
            if capture is not None and capture.last is not None:
                pf = capture.last
                row["bake"] = dict(pf.stats)
                row["rays_traced"] = int(pf.baker.stats.rays_traced)
                bakes.append(pf)
                if len(bakes) > 1:
                    bakes.pop(0)
            rows.append(row)
            spent = time.perf_counter() - start
            if budget and len(rows) >= 2 and len(rows) < len(frames) and spent + wall > budget:
                break
        gen.close()
    return {"rows": rows, "missing_probes": probes.missing, "last_bake": bakes[-1] if bakes else None}


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def appc_split(kind: str, row: dict) -> dict:
    """One frame's seconds on App. C's split (see the mapping in the table's notes)."""
    s, p, wall = row["stages"], row["probes"], row["wall"]
    untimed = max(wall - sum(s.values()), 0.0)
    out = dict.fromkeys(APPC, 0.0)
    if kind == "student":
        feats = s.get("features", 0.0)
        bake = row.get("bake", {})
        texels = min(bake.get("texels", 0.0), feats)
        threads = sum(bake.get(k, 0.0) for k in ("env", "cull", "trace", "transport", "shade"))
        share = bake.get("trace", 0.0) / threads if threads > 0 else 0.0
        gbuffer = min(p.get("gbuffer", 0.0), s.get("geometry", 0.0))
        out["pose/joints"] = s.get("geometry", 0.0) - gbuffer
        out["visibility"] = (feats - texels) * share
        out["UV sampling/transport"] = feats - out["visibility"]
        out["decoder"] = s.get("decoder", 0.0)
        out["compositing"] = s.get("composite", 0.0) + gbuffer
        out["untimed"] = untimed
    elif kind in ("linear", "teacher"):
        comp = min(p.get("composite", 0.0), untimed)
        gbuffer = min(p.get("gbuffer", 0.0), s.get("geometry", 0.0))
        shading = min(p.get("shading features", 0.0), s.get("network", 0.0))
        out["pose/joints"] = s.get("geometry", 0.0) - gbuffer
        out["visibility"] = s.get("visibility", 0.0)
        out["UV sampling/transport"] = s.get("inputs", 0.0) + shading
        out["decoder"] = s.get("network", 0.0) - shading
        out["compositing"] = comp + gbuffer
        out["untimed"] = untimed - comp
    else:
        trace = p.get("trace", 0.0)
        out["pose/joints"] = untimed
        out["visibility"] = s.get("scene", 0.0) + s.get("buried", 0.0) + trace
        out["compositing"] = s.get("gbuffer", 0.0)
        out["UV sampling/transport"] = max(sum(s.values()) - out["visibility"]
                                           - out["compositing"], 0.0)
    return out


def summarize(kind: str, run: dict) -> dict:
    """First frame apart; median and p95 (ms) of every stage, the App. C split and the
    wall time over the frames after it; frames/s = those frames / their wall seconds."""
    rows = run["rows"]
    first, steady = rows[0], rows[1:] or rows[:1]

    def stats(values):
        v = 1e3 * np.asarray(values, np.float64)
        return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
                "mean": float(np.mean(v))}

    stage_names = list(dict.fromkeys(k for r in rows for k in r["stages"]))
    probe_names = list(dict.fromkeys(k for r in rows for k in r["probes"]))
    split = [appc_split(kind, r) for r in rows]
    out = {
        "frames_timed": len(rows), "frames": [r["frame"] for r in rows],
        "first_ms": {"wall": 1e3 * first["wall"],
                     **{k: 1e3 * first["stages"].get(k, 0.0) for k in stage_names},
                     **{k: 1e3 * v for k, v in split[0].items()}},
        "stages": {k: stats([r["stages"].get(k, 0.0) for r in steady]) for k in stage_names},
        "probes": {k: stats([r["probes"].get(k, 0.0) for r in steady]) for k in probe_names},
        "appc": {k: stats([sp[k] for sp in (split[1:] or split[:1])]) for k in APPC},
        "untimed": stats([max(r["wall"] - sum(r["stages"].values()), 0.0) for r in steady]),
        "wall": stats([r["wall"] for r in steady]),
        "frames_per_s": len(steady) / sum(r["wall"] for r in steady),
        "passes": int(np.median([r["passes"] for r in rows])),
        "coverage": float(np.mean([r["coverage"] for r in rows])),
        "missing_probes": run["missing_probes"],
    }
    if kind == "student":
        bake = [r.get("bake", {}) for r in steady]
        out["bake_thread_ms"] = {k: stats([b.get(k, 0.0) for b in bake])
                                 for k in ("cull", "trace", "transport", "shade")}
        out["rays_traced"] = float(np.median([r.get("rays_traced", 0) for r in steady]))
    return out


def same_rays_embree(pf, repeat: int = 3) -> dict:
    """Raw embree on exactly the rays one frame's student bake traced (its visibility
    cache's traced pairs: lifted receiver → grid direction), one call, best of
    ``repeat``; against the bake's own rays per trace thread-second."""
    from relight_cli.visibility import trace_threads
    cache = pf.baker.cache
    rows, cols = np.nonzero(cache.traced)
    origins = cache.ray_origins()[rows].astype(np.float64)
    dirs = cache.directions[cols]
    best = np.inf
    cache.scene.occluded(origins[:16], dirs[:16])
    for _ in range(repeat):
        t0 = time.perf_counter()
        cache.scene.occluded(origins, dirs)
        best = min(best, time.perf_counter() - t0)
    trace = pf.stats.get("trace", 0.0)
    return {"rays": int(len(rows)), "raw_seconds": float(best),
            "raw_mrays": len(rows) / best / 1e6,
            "bake_trace_thread_seconds": float(trace),
            "bake_mrays_per_thread_second": (len(rows) / trace / 1e6) if trace > 0 else None,
            "trace_threads": trace_threads()}


def thread_check(kind: str, factory, frames: list, threads: int) -> dict:
    """The same job over a few frames on ``threads`` torch threads (then restored)."""
    import torch
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        run = run_job(kind, factory, frames, 0.0)
    finally:
        torch.set_num_threads(before)
    walls = [r["wall"] for r in run["rows"][1:]] or [run["rows"][0]["wall"]]
    return {"model": kind, "threads": threads, "frames": len(run["rows"]),
            "median_ms": 1e3 * float(np.median(walls)),
            "stages_median_ms": {k: 1e3 * float(np.median([r["stages"].get(k, 0.0)
                                                           for r in run["rows"][1:]]))
                                 for k in run["rows"][0]["stages"]}}


def pose_independent_costs(hand, envmap, texes, grid) -> dict:
    """Work the jobs repeat every frame although it does not depend on the pose: the UV
    rasterization of the fine mesh at each texture size, the env map's discretization."""
    from relight_cli.envmap import discretize_env
    from relight_cli.uvraster import rasterize_uv
    mesh = hand.mesh("fine")
    out = {}
    for n in sorted(set(texes)):
        t0 = time.perf_counter()
        rasterize_uv(mesh.uv, mesh.faces_uv, (n, n))
        out[f"rasterize_uv {n}²"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    discretize_env(envmap, *grid)
    out[f"discretize_env {grid[1]}×{grid[0]}"] = time.perf_counter() - t0
    return out


# ------------------------------------------------------------------ one process vs K


def cli_compare(work: Path, hand_path: str, env_spec: str, cam_path: Path, models: dict,
                kinds, k: int, threads: int | None, quick: bool, extrapolate: int = 300) -> dict:
    """``relight relight --frames 0:K`` once against K ``--frame k`` calls, per kind (the
    processes get ``OMP_NUM_THREADS`` = this run's torch threads)."""
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    h, w = env_grid(quick)
    out = {}
    for kind in kinds:
        base = ["relight", hand_path, env_spec, "--model", kind, "--camera", str(cam_path), "-q"]
        if quick:
            base += ["--env-res", f"{w}x{h}"]
        if kind != "physical":
            base[5:5] = ["--checkpoint", models[kind]["path"]]
        folder = work / f"cli_{kind}"
        folder.mkdir(exist_ok=True)
        seq = base + ["--frames", f"0:{k}", "-o", str(folder / "seq_{frame:04d}.exr")]
        t0 = time.perf_counter()
        subprocess.run(relight_exe() + seq, check=True, env=env)
        seq_wall = time.perf_counter() - t0
        singles = []
        for f in range(k):
            t0 = time.perf_counter()
            subprocess.run(relight_exe() + base + ["--frame", str(f), "-o",
                                                   str(folder / f"one_{f:04d}.exr")],
                           check=True, env=env)
            singles.append(time.perf_counter() - t0)
        mean = float(np.mean(singles))
        startup = (k * mean - seq_wall) / (k - 1) if k > 1 else float("nan")
        per_frame = mean - startup
        if not per_frame > 0:              # noise larger than a frame: no extrapolation
            per_frame = float("nan")
        out[kind] = {"k": k, "sequence_wall": seq_wall, "single_walls": singles,
                     "singles_total": float(np.sum(singles)), "single_mean": mean,
                     "startup_per_call": startup, "per_frame_in_sequence": per_frame,
                     "extrapolated_frames": extrapolate,
                     "extrapolated_sequence": startup + extrapolate * per_frame,
                     "extrapolated_singles": extrapolate * mean,
                     "command_sequence": " ".join(_shown(seq, work)),
                     "command_single": " ".join(_shown(base + ["--frame", "K", "-o",
                                                               "one_K.exr"], work))}
    return out


def _shown(args, work: Path) -> list:
    """A command line as recorded: work-folder paths by their file name only."""
    out = []
    for a in args:
        a = str(a)
        if a.startswith(str(work)):
            a = Path(a).name
        elif a.startswith(str(B.ROOT.parent)):
            a = "../" + str(Path(a).relative_to(B.ROOT.parent))
        out.append(a)
    return ["relight", *out]


# ------------------------------------------------------------------ report


def ms(x: float) -> str:
    """Milliseconds for a table: 3 significant digits, thousands grouped."""
    return f"{x:,.0f}" if x >= 100 else f"{x:.1f}" if x >= 1 else f"{x:.2f}"


def cell(st: dict) -> str:
    return f"{ms(st['median'])} / {ms(st['p95'])}"


#: App. C stages a model does not have (its cell shows —).
ABSENT = {"physical": ("decoder", "untimed")}


def markdown(report: dict) -> list:
    from relight_cli.visibility import trace_threads
    m = report["machine"]
    a = report["args"]
    lines = ["# Sequences: per-frame cost of relighting a real hand motion (one process)", "",
             B.run_description(report["command"], report["quick"], report["wall_seconds"]), "",
             B.machine_line(m), "",
             f"**Load.** Load average {report['load_start']} at the start, "
             f"{report['load_end']} at the end (1, 5, 15 min) on {m['cpus']} cores: above the "
             f"core count other jobs shared the machine and the timings are upper bounds. "
             f"torch ran on {m.get('torch_threads')} thread(s); ray tracing on "
             f"{trace_threads()}.  The student's decoder runs in float32 with channels_last "
             f"weights (`relight --precision float32`); the CLI's default `auto` picks "
             f"bfloat16 on CPUs with native bf16, about 2× faster at the paper's widths "
             f"(benchmarks/results/student.md).", "",
             "**The learned models are untrained** (random initialization, built at the papers' "
             "widths through the Python API, written with `make_checkpoint` and loaded back by "
             "the CLI's loaders): their costs are what the architectures cost; their images "
             "mean nothing.", "",
             "## Inputs", "",
             "| recording | frames | fitted frames | MPJPE (mm) | fit wall (s) | command |",
             "|---|---|---|---|---|---|"]
    for name, f in report["recordings"].items():
        lines.append(f"| {name} | {f['frames']} | {f['fitted_frames']} | {f['mpjpe_mm']:.2f} | "
                     f"{f['fit_seconds']:.1f} | `{f['command']}` |")
    sc = report["scenes"]
    lines += ["", f"Every recording holds one right hand (Leap ids: one per file). Scenes: "
              f"**one hand** = `{a['recording']}` as fitted; **two hands** = the same fit plus its "
              f"mirror image 0.2 m beside it (`relight_cli.hand.scene.two_hands`, exactly what "
              f"`fit-geometry --two-hands` adds; both hands move, mirrored). Frames "
              f"{sc['one']['frames'][0]}…{sc['one']['frames'][-1]} of the recording "
              f"({len(sc['one']['frames'])} selected: `--frames {a['frames']}`, capped at the "
              f"recording's length), in order, "
              + (f"each job stopped early once it had spent `--budget {a['budget']:g}` s (at least "
                 f"2 frames: see *frames timed*)" if a["budget"] else "every frame rendered")
              + f". Env map: {report['env']}, on {report['env_grid']} (W×H) directions (the CLI's "
              f"`--env-res`; the student on its own grid, {report['student_grid']}). "
              f"Camera: fixed, {a['size']}×{a['size']}, "
              f"`preview_camera` framing five frames spread over the selection "
              f"(hands cover {100 * sc['one']['coverage']:.0f} % / {100 * sc['two']['coverage']:.0f} % "
              f"of the pixels, one / two hands).", "",
              "| model | built as | parameters | checkpoint load (s) |", "|---|---|---|---|"]
    for kind, d in report["models"].items():
        params = f"{d['parameters']:,}" if "parameters" in d else "—"
        load = f"{d['load_seconds']:.2f}" if "load_seconds" in d else "—"
        lines.append(f"| {kind} | {d['describe']} | {params} | {load} |")
    res = report["results"]
    lines += ["", "## Per-frame cost on RelightableHands App. C's split", "",
              "ms per frame, **median / p95** over the frames after the first (the first frame, "
              "the warm-up, in its own column); frames/s = those frames over their wall time. "
              "Columns are App. C's stages: pose/joints · visibility (ray tracing) · UV "
              "sampling / transport · decoder · compositing; *untimed* is the frame's wall time "
              "that no stage reports (mapping below).", "",
              "| model | hands | frames timed | first frame | pose/joints | visibility | UV sampling / "
              "transport | decoder | compositing | untimed | wall per frame | frames/s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for kind in report["models"]:
        for scene in ("one", "two"):
            r = res.get(f"{kind}/{scene}")
            if r is None:
                continue
            hands = 1 if scene == "one" else 2
            lines.append(f"| {kind} | {hands} | {r['frames_timed']} of {len(sc[scene]['frames'])} | "
                         f"{ms(r['first_ms']['wall'])} | "
                         + " | ".join("—" if k in ABSENT.get(kind, ()) else cell(r["appc"][k])
                                      for k in APPC) +
                         f" | {cell(r['wall'])} | {r['frames_per_s']:.3g} |")
    lines.append("| paper's student (V100) | 1 | — | — | 0.3 | 2.7 | 1.5 | 15.8 | — | — | 21 "
                 "(two hands 32) | 48 |")
    lines += ["", "Mapping of each job's own stages (`FrameRender.seconds`) onto App. C:", "",
              "- **student** (`relight_cli.jobs.relight_hand.student`): *geometry* → pose/joints "
              "(posing the fine mesh and the coarse proxy by LBS, the proxy's feature-baker set-up "
              "with its embree BVH), except the view's G-buffer cast inside it (a timing probe "
              "around `render_gbuffer`; the job is not changed) → compositing; *features* "
              "(bake-features' maps) → "
              "visibility + UV sampling/transport: its texel-map step (`texels`, wall) is UV "
              "sampling, the rest is split between visibility and transport in proportion to the "
              "bake's own thread-seconds of `trace` against `cull + transport + shade` (the bake "
              "reports thread-seconds on its tracing threads, not wall); *decoder* → decoder "
              "(includes the joint-feature network J_s, App. C's 0.3 ms *joint features*, and "
              "the env normalization); *composite* → compositing.",
              "- **linear** and **teacher** (`learned`): *geometry* → pose/joints (posing, the "
              "texel G-buffer at the model's texture size), except the view's G-buffer cast "
              "(probe `render_gbuffer`) → compositing; *visibility* → "
              "visibility (each texel towards each lit env direction, traced); teacher *inputs* "
              "(texel-aligned light/view direction maps) → UV sampling/transport; linear "
              "*network* is split by timing probes wrapped around the functions it calls (the "
              "job is not changed): GGX shading features per light (`shading_features`, "
              "`refined_normals`, `map_to_texels`, `texels_to_map`) → UV sampling/transport, the "
              "rest (F_G, F_nl, F_l) → decoder; the textures' lookup through the G-buffer "
              "(`composite`, a probe; outside every job stage) → compositing with the G-buffer.",
              "- **physical**: no network. *scene* + *buried* + the env visibility rays traced "
              "(a probe on `VisibilityCache.require`, inside *direct*/*shade*) → visibility; "
              "*texels* + *direct* + *sss* + *shade* less those rays → transport/shading; "
              "*gbuffer* → compositing; the untimed remainder (posing by LBS, the image resolve) "
              "→ pose/joints.", ""]
    for kind in report["models"]:
        rs = {scene: res.get(f"{kind}/{scene}") for scene in ("one", "two")}
        if not any(rs.values()):
            continue
        names = list(dict.fromkeys(k for r in rs.values() if r for k in r["stages"]))
        probes = list(dict.fromkeys(k for r in rs.values() if r for k in r["probes"]))
        lines += [f"### {kind}: the job's own stages (ms: first frame, median / p95 after it)", "",
                  "| stage | one hand: first | one hand: median / p95 | two hands: first | "
                  "two hands: median / p95 |", "|---|---|---|---|---|"]
        for name in names:
            cells = []
            for scene in ("one", "two"):
                r = rs[scene]
                cells += ([ms(r["first_ms"].get(name, 0.0)), cell(r["stages"][name])]
                          if r and name in r["stages"] else ["—", "—"])
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        for name in probes:
            cells = []
            for scene in ("one", "two"):
                r = rs[scene]
                cells += ["", cell(r["probes"][name])] if r and name in r["probes"] else ["", "—"]
            lines.append(f"| *probe: {name}* | " + " | ".join(cells) + " |")
        cells = []
        for scene in ("one", "two"):
            r = rs[scene]
            cells += [ms(r["first_ms"]["wall"]), cell(r["wall"])] if r else ["—", "—"]
        lines.append("| **wall per frame** | " + " | ".join(cells) + " |")
        if kind == "student":
            for stage in ("cull", "trace", "transport", "shade"):
                cells = []
                for scene in ("one", "two"):
                    r = rs[scene]
                    cells += ["", cell(r["bake_thread_ms"][stage])] if r else ["", "—"]
                lines.append(f"| *bake thread-seconds: {stage}* | " + " | ".join(cells) + " |")
        passes = [f"{rs[s]['passes']}" for s in ("one", "two") if rs[s]]
        if kind in ("teacher", "linear"):
            lines += ["", f"Lights summed per frame (passes counted by the job): "
                      f"{' / '.join(passes)} (one / two hands)."]
        missing = sorted({p for r in rs.values() if r for p in r["missing_probes"]})
        if missing:
            lines += ["", f"Probes not found in this checkout (their split is left in the "
                          f"stage that contains them): {', '.join(missing)}."]
        lines.append("")
    lim = report["limits"]
    e = report.get("embree_same_rays")
    lines += ["## Machine limits (this run)", "",
              "| measure | value |", "|---|---|",
              f"| fp32 GEMM (torch.mm 1024²) | {m['gemm_gflops']:.1f} GFLOP/s |",
              f"| fp32 dense 3×3 conv (torch, best of {len(B.CONV_SHAPES)} shapes × 2 layouts) | "
              f"{m.get('conv_gflops', float('nan')):.1f} GFLOP/s |",
              f"| memory copy | {m['memory_gbs']:.1f} GB/s |",
              f"| raw embree, random rays inside a 20k-triangle sphere (`_common.embree_mrays`) | "
              f"{m['embree_mrays']:.2f} Mrays/s |"]
    if e:
        lines += [f"| raw embree, **the same rays** as one frame's student feature bake "
                  f"({e['rays']:,} rays, one call, one thread) | {e['raw_mrays']:.2f} Mrays/s |",
                  f"| the bake's own trace stage on them | "
                  + (f"{e['bake_mrays_per_thread_second']:.2f} Mrays per thread-second "
                     f"({e['trace_threads']} tracing threads) |" if e["bake_mrays_per_thread_second"]
                     else "— |")]
    if m.get("peak_measurements", 1) > 1:
        lines.append(f"| GEMM / conv measured again at the end (best kept) | "
                     f"{m['gemm_gflops']:.1f} / {m['conv_gflops']:.1f} GFLOP/s |")
    lines += ["", "Pose-independent work the jobs redo every frame (measured once here):", ""]
    for name, seconds in lim.items():
        lines.append(f"- `{name}`: {1e3 * seconds:.1f} ms")
    cli = report.get("cli")
    if cli:
        lines += ["", "## One process for K frames against one call per frame (CLI subprocesses)", "",
                  "Wall-clock seconds of `relight relight` processes writing EXRs (one hand). "
                  "The per-call start-up is derived: a single call costs start-up + one frame, the "
                  "sequence start-up + K frames, so start-up = (K·single − sequence)/(K − 1); it "
                  "holds the interpreter, imports, reading the hand, env map and checkpoint and "
                  "preparing model, materials and env. **The 300-frame columns are an "
                  "extrapolation** (start-up + 300 × the per-frame cost), not a measurement.", "",
                  "| model | K | one process, K frames | K single calls | mean single call | "
                  "per-call start-up | per frame in the sequence | 300 frames, one process "
                  "(extrapolated) | 300 single calls (extrapolated) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for kind, c in cli.items():
            ok = np.isfinite(c["per_frame_in_sequence"])
            lines.append(f"| {kind} | {c['k']} | {c['sequence_wall']:.1f} s | "
                         f"{c['singles_total']:.1f} s | {c['single_mean']:.2f} s | "
                         + (f"{c['startup_per_call']:.2f} s | {c['per_frame_in_sequence']:.2f} s | "
                            f"{c['extrapolated_sequence'] / 60:.1f} min | " if ok else
                            "n/a (noise larger than the difference) | n/a | n/a | ")
                         + f"{c['extrapolated_singles'] / 60:.1f} min |")
        lines += [""] + [f"- {kind}: `{c['command_sequence']}` against K × "
                         f"`{c['command_single']}`" for kind, c in cli.items()]
    lines += ["", "## Observations", ""] + report["observations"] + ["", "Plot: sequence.png."]
    return lines


def observations(report: dict) -> list:
    """Measured facts worth acting on (nothing here is changed by the benchmark)."""
    out = []
    res = report["results"]
    for key, r in res.items():
        kind, scene = key.split("/")
        shares = {k: r["appc"][k]["median"] for k in APPC}
        total = sum(shares.values())
        top = max(shares, key=shares.get)
        if total > 0:
            out.append(f"- {kind}, {'one hand' if scene == 'one' else 'two hands'}: "
                       f"{top} dominates ({100 * shares[top] / total:.0f} % of the median frame, "
                       f"{ms(shares[top])} ms); first frame {ms(r['first_ms']['wall'])} ms against "
                       f"a median {ms(r['wall']['median'])} ms.")
    for kind in report["models"]:
        one, two = res.get(f"{kind}/one"), res.get(f"{kind}/two")
        if one and two:
            out.append(f"- {kind}: two hands cost {two['wall']['median'] / one['wall']['median']:.2f}× "
                       f"one hand per frame.")
    lim = report["limits"]
    raster = {k: v for k, v in lim.items() if k.startswith("rasterize_uv")}
    if raster:
        out.append("- Per frame but pose independent: the physical and learned jobs build "
                   "their texel surfaces (`HandRenderer` / `PoseTexels`) without shared UV "
                   "rasterizations, so each frame rasterizes the fine mesh's UV layout again "
                   "(once per hand: " + ", ".join(f"{k} {1e3 * v:.0f} ms" for k, v in raster.items())
                   + "); the student's job shares them across frames.")
    disc = [v for k, v in lim.items() if k.startswith("discretize_env")]
    if disc and "physical" in report["models"]:
        out.append(f"- The physical job hands the renderer the env map itself, which each "
                   f"frame's new `HandRenderer` discretizes again "
                   f"({1e3 * disc[0]:.0f} ms per frame for this map); the learned jobs get it "
                   f"discretized once.")
    tc = report.get("thread_check")
    one = res.get(f"{tc['model']}/one") if tc else None
    if tc and one:
        out.append(f"- Threads: the {tc['model']} (one hand) on {tc['threads']} torch threads "
                   f"took {ms(tc['median_ms'])} ms per frame (median of {tc['frames'] - 1}) against "
                   f"{ms(one['wall']['median'])} ms on {report['machine'].get('torch_threads')} "
                   f"in the table ({tc['median_ms'] / one['wall']['median']:.2f}×): on this "
                   f"loaded machine a second torch thread waits for a core the other jobs hold.")
    e = report.get("embree_same_rays")
    if e and e.get("bake_mrays_per_thread_second"):
        out.append(f"- The student's bake traces its rays at "
                   f"{100 * e['bake_mrays_per_thread_second'] / e['raw_mrays']:.0f} % of raw "
                   f"embree's rate on the same rays (per thread-second).")
    return out


def write_plot(path: Path, report: dict) -> None:
    """Frames/s per model and scene; each model's App. C shares; one process vs calls."""
    res = report["results"]
    cli = report.get("cli") or {}
    fig, axes = B.figure(3 if cli else 2, width=6.0, height=4.6)
    keys = [k for k in (f"{m}/{s}" for m in report["models"] for s in ("one", "two")) if k in res]
    labels = [f"{k.split('/')[0]}, {'1 hand' if k.endswith('one') else '2 hands'}" for k in keys]
    ax = axes[0]
    fps = [res[k]["frames_per_s"] for k in keys]
    colors = ["C0" if k.endswith("one") else "C1" for k in keys]
    ax.barh(labels, fps, color=colors)
    for y, v in enumerate(fps):
        ax.annotate(f"{v:.3g}", (v, y), textcoords="offset points", xytext=(3, -3), fontsize=7)
    ax.axvline(1000 / PAPER_TOTAL[1], color="0.4", linestyle="--", linewidth=1)
    ax.annotate("paper's student,\nV100, 1 hand", (1000 / PAPER_TOTAL[1], 0), fontsize=7,
                color="0.3", ha="right", va="center", textcoords="offset points", xytext=(-3, 0))
    ax.set_xscale("log")
    ax.invert_yaxis()
    ax.set_xlabel("frames/s after the first frame (log)")
    ax.set_title(f"frames/s, one process per sequence ({report['args']['size']}² view)", fontsize=10)
    ax.grid(True, axis="x", which="both", alpha=0.4)
    ax = axes[1]
    bars = [(lab, {s: res[k]["appc"][s]["median"] for s in APPC}) for lab, k in zip(labels, keys)]
    bars.append(("paper's student (V100), 1 hand", dict(PAPER_MS)))
    left = np.zeros(len(bars))
    for stage in APPC:
        shares = []
        for _, d in bars:
            total = sum(d.values())
            shares.append(100 * d.get(stage, 0.0) / total if total else 0.0)
        ax.barh([b[0] for b in bars], shares, left=left, label=stage)
        left += shares
    for y, (_, d) in enumerate(bars):
        ax.annotate(f"{ms(sum(d.values()))} ms", (100, y), textcoords="offset points",
                    xytext=(3, -3), fontsize=7)
    ax.set_xlim(0, 125)
    ax.invert_yaxis()
    ax.set_xlabel("% of the median frame (label: its ms)")
    ax.set_title("App. C split of a frame", fontsize=10)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.45, -0.13), ncol=3)
    ax.grid(True, axis="x", alpha=0.4)
    if cli:
        ax = axes[2]
        names = list(cli)
        x = np.arange(len(names))
        width = 0.2
        series = [("one process, K frames", [cli[n]["sequence_wall"] for n in names], "C0"),
                  ("K single calls", [cli[n]["singles_total"] for n in names], "C1"),
                  ("one process, 300 (extrapolated)",
                   [cli[n]["extrapolated_sequence"] for n in names], "C0"),
                  ("300 single calls (extrapolated)",
                   [cli[n]["extrapolated_singles"] for n in names], "C1")]
        for i, (name, values, color) in enumerate(series):
            extrapolated = "extrapolated" in name
            ax.bar(x + (i - 1.5) * width, values, width, label=name, color=color,
                   alpha=0.45 if extrapolated else 1.0, hatch="//" if extrapolated else None,
                   edgecolor=color)
            for xi, v in zip(x + (i - 1.5) * width, values):
                if np.isfinite(v) and v > 0:
                    ax.annotate(f"{v:.0f}", (xi, v), ha="center", fontsize=6,
                                textcoords="offset points", xytext=(0, 2))
        ax.set_xticks(x)
        ax.set_xticklabels([f"{n} (K = {cli[n]['k']})" for n in names])
        ax.set_yscale("log")
        ax.set_ylabel("wall seconds (log)")
        ax.set_title("relight --frames 0:K against K calls (CLI)", fontsize=10)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
        ax.grid(True, axis="y", which="both", alpha=0.4)
    B.save(fig, path, report["machine"])


# ------------------------------------------------------------------ main


def main():
    ap = B.parser(__doc__, "5 frames, tiny widths and textures, a 96×96 view, K = 2")
    ap.add_argument("--recording", default="pinch", choices=RECORDINGS,
                    help="the recording the tables render [default: pinch, 307 frames]")
    ap.add_argument("--frames", type=B.integer(1), default=300,
                    help="frames per sequence (capped at the recording's) [default: 300]")
    ap.add_argument("--budget", type=B.number(0), default=90.0,
                    help="seconds one job may spend before it stops early (≥ 2 frames; "
                         "0: no limit) [default: 90]")
    ap.add_argument("--k", type=B.integer(0), default=10,
                    help="frames of the CLI comparison (one process against K calls) [default: 10]")
    ap.add_argument("--models", default=",".join(MODELS),
                    help=f"comma-separated subset of {', '.join(MODELS)}")
    ap.add_argument("--size", type=B.integer(1), default=256, help="view size N×N [default: 256]")
    ap.add_argument("--linear-tex", type=B.integer(1), default=256,
                    help="the linear model's texture (paper 1024) [default: 256]")
    ap.add_argument("--teacher-tex", type=B.integer(1), default=128,
                    help="the OLAT teacher's texture (paper 1024) [default: 128]")
    ap.add_argument("--report", action="store_true",
                    help="only rewrite sequence.md and sequence.png from --out's sequence.json")
    ap.add_argument("--threads", type=B.integer(0), default=1,
                    help="torch threads of this run and of its CLI subprocesses (0: torch's "
                         "default) [default: 1: on the shared 2-core machine torch's 2 "
                         "threads ran the linear model's small element-wise ops up to 90× "
                         "slower, see the thread check in the table]")
    args = ap.parse_args()
    wanted = [m.strip() for m in args.models.split(",") if m.strip()]
    bad = [m for m in wanted if m not in MODELS]
    if bad:
        ap.error(f"unknown model(s): {', '.join(bad)}")
    if args.quick:
        args.frames, args.size, args.k, args.budget = 5, 96, 2, 0.0
    if args.report:        # the record is read (and refused if damaged) before anything
        B.check_out_dir("bench_sequence.py", args.out, "--out")
        report = B.read_report("bench_sequence.py", Path(args.out) / "sequence.json")
    out = B.start(args, "bench_sequence.py")
    if args.report:
        if "physical" in report.get("models", {}):
            report["models"]["physical"]["describe"] = physical_describe(report["quick"])
        write_outputs(out, report)
        return
    if not (LEAP / f"{args.recording}.json").is_file():      # make benchmarks goes on
        print(f"bench_sequence.py: skipped: the Leap recordings are not in {LEAP}",
              file=sys.stderr)
        return
    wall0 = time.perf_counter()
    threads = B.set_threads(args.threads or None)
    report = {"command": B.run_command("bench_sequence.py", sys.argv[1:]), "quick": args.quick,
              "args": {"recording": args.recording, "frames": args.frames,
                       "budget": args.budget, "k": args.k, "size": args.size,
                       "linear_tex": args.linear_tex, "teacher_tex": args.teacher_tex,
                       "models": wanted, "threads": threads},
              "load_start": B.load_average()}
    report["machine"] = B.machine_limits(embree=True, conv=True)
    work = Path(tempfile.mkdtemp(prefix="bench_sequence_"))
    try:
        from relight_cli.builtin_envs import builtin_envmap
        from relight_cli.formats.camera import write_cameras
        from relight_cli.formats.envmap import read_envmap
        from relight_cli.formats.hand_npz import read_hand, write_hand
        from relight_cli.hand.scene import two_hands

        names = [args.recording] if args.quick else list(RECORDINGS)
        report["recordings"] = fit_recordings(work, names, args.quick)
        one = read_hand(report["recordings"][args.recording]["path"])
        two = two_hands(one)
        write_hand(str(work / "two.npz"), two)
        if HDRI.is_file():
            env_spec, envmap = str(HDRI), read_envmap(str(HDRI))
            report["env"] = f"`{HDRI.name}` (Poly Haven, 1k)"
        else:
            env_spec, envmap = "builtin:studio", builtin_envmap("builtin:studio")
            report["env"] = "`builtin:studio`"
        frames = list(range(min(args.frames, one.n_frames)))
        models = build_models(work, one, wanted, args.quick, args.linear_tex, args.teacher_tex)
        h, w = env_grid(args.quick)
        report["env_grid"] = f"{w}×{h}"
        report["student_grid"] = (f"{models['student']['config'].env_res[1]}×"
                                  f"{models['student']['config'].env_res[0]}"
                                  if "student" in models else "—")
        report["models"] = {k: {kk: vv for kk, vv in v.items()
                                if kk in ("describe", "parameters", "load_seconds")}
                            for k, v in models.items()}
        report["scenes"], report["results"], cams = {}, {}, {}
        same_rays = None
        for scene, hand in (("one", one), ("two", two)):
            cam = fixed_camera(hand, frames, args.size)
            cams[scene] = cam
            report["scenes"][scene] = {"hands": len(hand.hands), "frames": frames,
                                       "camera": cam.to_json()}
            covers = []
            for kind in wanted:
                factory, prep = make_job(kind, hand, cam, models, envmap, args.quick)
                print(f"== {kind}, {len(hand.hands)} hand(s): up to {len(frames)} frames",
                      flush=True)
                run = run_job(kind, factory, frames, args.budget)
                summary = summarize(kind, run)
                summary["prepare_seconds"] = prep
                summary["per_frame"] = [{k: v for k, v in r.items() if k != "bake"}
                                        for r in run["rows"]]
                report["results"][f"{kind}/{scene}"] = summary
                covers.append(summary["coverage"])
                print(f"   {summary['frames_timed']} frames, first {ms(summary['first_ms']['wall'])} ms, "
                      f"median {ms(summary['wall']['median'])} ms, {summary['frames_per_s']:.3g} "
                      f"frames/s", flush=True)
                if kind == "student" and scene == "one" and run["last_bake"] is not None:
                    same_rays = same_rays_embree(run["last_bake"])
            report["scenes"][scene]["coverage"] = float(np.mean(covers)) if covers else 0.0
        report["embree_same_rays"] = same_rays
        texes = [64 if args.quick else 256]
        for kind in ("linear", "teacher"):
            if kind in models:
                texes.append(models[kind]["config"].tex_res)
        report["limits"] = pose_independent_costs(one, envmap, texes, env_grid(args.quick))
        if not args.quick and "student" in wanted and (os.cpu_count() or 1) != threads:
            factory, _ = make_job("student", one, cams["one"], models, envmap, False)
            print(f"== thread check: student, one hand, 5 frames on {os.cpu_count()} torch "
                  f"threads", flush=True)
            report["thread_check"] = thread_check("student", factory, frames[:5],
                                                  os.cpu_count() or 1)
        write_cameras(str(work / "cam.json"), [cams["one"]])
        kinds = [k for k in ("linear", "physical") if k in wanted]
        if kinds and args.k >= 1:
            print(f"== CLI: --frames 0:{args.k} against {args.k} single calls: "
                  f"{', '.join(kinds)}", flush=True)
            report["cli"] = cli_compare(work, report["recordings"][args.recording]["path"],
                                        env_spec, work / "cam.json", models, kinds, args.k,
                                        threads, args.quick)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not args.quick:
        B.flop_peak(report["machine"])          # again at the end: the best of both
    report["load_end"] = B.load_average()
    report["wall_seconds"] = time.perf_counter() - wall0
    for rec in report["recordings"].values():
        rec.pop("path", None)
    write_outputs(out, report)


def write_outputs(out: Path, report: dict) -> None:
    """sequence.json, sequence.md (with its observations) and sequence.png of a run."""
    report["observations"] = observations(report)
    (out / "sequence.json").write_text(json.dumps(report, indent=1, default=str) + "\n")
    lines = markdown(report)
    (out / "sequence.md").write_text("\n".join(lines) + "\n")
    write_plot(out / "sequence.png", report)
    print("\n".join(lines))


if __name__ == "__main__":
    B.run_main("bench_sequence.py", main)
