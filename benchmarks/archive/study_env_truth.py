"""How much of the OLAT teachers' env-map gap is their ground truth's: env renders whose
transport is integrated at mesh vertices against renders integrated where the LEDs are.

The teachers of study_teacher_inputs.py learn from LED frames, whose irradiance and
visibility the synthetic stage evaluates per texel, and render an env map as a sum of
distant lights (RelightableHands Eq. 2).  Captures made before ``synth-capture
--eval-env-space`` rendered their env-map ground truth with bake-features' per-vertex
transport, interpolated to texels: shadows and highlights under an env map then follow
the mesh's vertices while the LEDs' follow the texels, and no model of the LED frames can
reproduce that difference.  This study measures it twice:

* **The stage alone** (no model): on a held-out pose, each of ``--directions`` directions
  rendered as one direction of an env map and as an LED ``FAR`` metres away in the same
  direction (intensity scaled by r²), through camera 0 at the capture's own texture size;
  the relative MSE between the two is the superposition error of each ``env_space``.
* **The teachers**: every seed of each ``--teachers`` variant, trained once on the
  capture (study_teacher_inputs.py's cache, ``--work``), scored on the env renders of
  that capture (``vertices``) and on the
  same capture made again with ``eval_env_space: texels`` (identical LED frames, so the
  same training data; other env renders; each scored with its own ceiling, the perfect
  texture through the same compositing).

A difference is a verdict only when it exceeds max(2 σ over seeds, 0.2 dB), paired by
seed.  Writes ``env_truth.{md,json}`` to ``--out``.  Run (the teachers cached: about
15 min on 2 cores, most of it the two new captures)::

    .venv/bin/python benchmarks/study_env_truth.py --seeds 3 --workers 2 \\
        --teachers paper,shading,shading_l128 --work benchmarks/out/teacher_inputs \\
        --out benchmarks/results/converged/env_truth
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
import bench_presets as P  # noqa: E402
import study_teacher_inputs as T  # noqa: E402

SPACES = ("vertices", "texels")
#: the other ``train-teacher --model`` kinds, at their ``cpu`` preset (``--models``)
MODELS = ("ggx", "linear")
#: metres to the far LED of the superposition check (the stage's LEDs are 1.2 m away)
FAR = 100.0


def stage_of(variant: str, space: str, eval_poses: int | None = None) -> dict:
    """The capture settings a teacher variant is scored on in one env space; with
    ``eval_poses``, that many held-out env-render poses instead of the scale's (a
    capture of its own: its first renders are not the scale's images, measured)."""
    return {**T.STAGES.get(variant, {}), **({"eval_env_space": space} if space == "texels"
                                            else {}),
            **({"eval_poses": int(eval_poses)} if eval_poses else {})}


def poses_tag(eval_poses: int | None) -> str:
    """The cache-name tag of scores on a capture of ``eval_poses`` held-out env poses
    ("" for the scale's own)."""
    return f".poses{int(eval_poses)}" if eval_poses else ""


def superposition(capture: str, space: str, directions: int) -> list:
    """Per direction, the relative MSE (Σ(a − b)² / Σ b²) between the stage's render of one
    direction of an env map (``space``) and of a far LED in that direction, through
    camera 0's G-buffer at held-out pose 0, on the texture of the capture's own size."""
    import numpy as np
    import torch

    from relight_cli.envmap import DiscreteEnv, discretize_env
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.ceiling import Ceiling
    from relight_cli.neural.teacher import composite
    from relight_cli.render.shading import PointLights

    torch.set_num_threads(1)
    data = CaptureData(capture, 64, 0, True)
    shader = Ceiling(data).shader
    shader.settings = s = replace(shader.settings, eval_env_space=space)   # this one's own
    meshes = data.meshes(0, True)
    renderer = shader.renderer(meshes)
    texels = data.texels(0, True)
    gbuffer = data.gbuffer(0, data.capture.cameras[0], True)
    grid = discretize_env(data.env_map(next(iter(data.capture.evaluation["envs"]))),
                          *s.eval_env_res)
    mask = gbuffer.coverage(0) > 0.5
    centre = np.mean(meshes[0].vertices, 0)
    # the grid's cells nearest to evenly spread directions (Fibonacci), lit from each once
    i = np.arange(directions) + 0.5
    z = 1 - 2 * i / directions
    phi = i * np.pi * (3 - np.sqrt(5))
    want = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    out = []

    def image(lighting):
        radiance = shader.texel_radiance(renderer, lighting, [texels.surfaces[0]], gbuffer.eye)
        tex = torch.from_numpy(texels.to_maps(0, radiance[0].astype(np.float32)))
        return composite([tex], gbuffer).numpy()

    for d in want:
        m = int(np.argmax(grid.directions @ d))
        rad = np.zeros_like(grid.radiance)
        rad[m] = 1.0 / grid.solid_angle[m]                 # L Δω = 1 from that cell
        env = image(renderer.light(env=DiscreteEnv(grid.directions, grid.solid_angle, rad,
                                                   grid.height, grid.width)))
        led = image(renderer.light(PointLights((centre + FAR * grid.directions[m])[None],
                                               np.full((1, 3), FAR * FAR))))
        energy = float(np.sum(led[mask] ** 2))
        if energy > 0:
            out.append(float(np.sum((env[mask] - led[mask]) ** 2)) / energy)
    return out


def run_model(work: Path, capture: Path, model: str, seed: int, log) -> dict:
    """``relight train-teacher CAPTURE --preset cpu --model MODEL`` once (cached as
    work/MODEL_sSEED.*, beside study_teacher_inputs.py's OLAT runs)."""
    name = f"{model}_s{seed}"
    if (work / f"{name}.done.json").is_file():
        return json.loads((work / f"{name}.done.json").read_text())
    argv = ["train-teacher", str(capture), "--preset", "cpu", "--model", model, "--seed",
            str(seed), "-o", str(work / f"{name}.pt"), "--metrics-out",
            str(work / f"{name}.json"), "-q"]
    return T.run_once(work, name, argv, "study_env_truth.py", log)


def score_env(work: str, capture: str, variant: str, seed: int, space: str,
              tag: str = "") -> dict:
    """The teacher's (or linear model's) env split on ``capture`` (cached, ``tag`` in the
    name: :func:`poses_tag`): {psnr, ceiling, gap, samples}."""
    path = Path(work) / f"{variant}_s{seed}.env_{space}{tag}.json"
    if path.is_file():
        return json.loads(path.read_text())
    import torch

    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.neural.evaluate import evaluate_capture, load_hand_model
    torch.set_num_threads(1)
    model = load_hand_model(read_checkpoint(str(Path(work) / f"{variant}_s{seed}.pt")))
    s = evaluate_capture(capture, [model], ["env"])["env"]
    out = {"psnr": s["psnr"], "ceiling": s["ceiling"]["psnr"], "gap": s["gap_to_ceiling"],
           "samples": s["samples"]}
    P.B_write(path, out)
    return out


def score_student(students: str, teachers: str, capture: str, variant: str, seed: int,
                  space: str, grid=None) -> dict:
    """A study_student_env.py student (its cache ``students``) against the env renders of
    ``capture`` (cached): {psnr, ceiling, gap, samples} over every render, as the
    ``distill`` command's own ``vs_ground_truth`` scores them (the perfect texture at the
    student's N through the same compositing for the ceiling); its features on the env
    grid ``grid`` (H, W; default its training grid ``env_res``)."""
    tag = "" if grid is None else f".grid{grid[0]}x{grid[1]}"
    path = Path(students) / f"{variant}_s{seed}.gt_{space}{tag}.json"
    if path.is_file():
        cached = json.loads(path.read_text())
        if "mse" in cached:          # scores cached before the MSE was kept: again
            return cached
    import numpy as np
    import torch

    import study_student_env as E
    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.inputs import load_envmap
    from relight_cli.neural import distill as DI
    from relight_cli.neural.ceiling import ceiling_of
    from relight_cli.neural.checkpoints import student_model
    from relight_cli.neural.scores import attach_ceiling
    torch.set_num_threads(1)
    model, config = student_model(read_checkpoint(str(Path(students) / f"{variant}_s{seed}.pt"),
                                                  kind="student"))
    model.eval()
    grid = tuple(grid or config.env_res)
    teacher = Path(teachers) / f"{E.teacher_of(variant)}_s{seed}.pt"
    data, targets = E._targets(str(teacher), capture, None)
    envs = E._env_specs()
    specs = envs["train"] + envs["eval"]
    n_train = len(envs["train"])
    grids = [discretize_env(load_envmap(s), *config.env_res) for s in specs]
    task = DI.StudentTask(data, config, targets, grids, list(range(n_train)),
                          list(range(n_train, len(specs))), specs)
    ceiling = ceiling_of(data)
    rows, best = [], []
    for render in data.splits()["env"]:
        pose, env_name, camera, gt, mask = data.env_target(render[1])
        denv = discretize_env(data.env_map(env_name), *grid)
        with torch.no_grad():
            pred = task.render(model, pose, camera.name, denv, "cpu", held_out=True)
        m = DI._metrics(pred.numpy(), gt, mask)
        if m:
            rows.append(m)
            texels = DI._student_texels(task, pose)
            best.append(ceiling.score(render, [texels] * texels.n_hands,
                                      data.gbuffer(pose, camera, held_out=True), gt, mask))
    s = attach_ceiling({"psnr": float(np.mean([r["psnr"] for r in rows])),
                        "mse": float(np.mean([r["mse"] for r in rows])),
                        "samples": len(rows)}, best)
    out = {"psnr": s["psnr"], "mse": s["mse"], "ssim": float(np.mean([r["ssim"] for r in rows])),
           "ceiling": s["ceiling"]["psnr"], "ceiling_mse": s["ceiling"]["mse"],
           "gap": s["gap_to_ceiling"], "samples": s["samples"]}
    P.B_write(path, out)
    return out


def _stats(values) -> list:
    import numpy as np
    v = np.asarray(values, float)
    return [float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0]


def summarize(scores: dict) -> dict:
    """scores[variant][space] = per-seed {psnr, ceiling, gap} → per variant and space the
    mean ± std of PSNR and gap, and texels − vertices paired by seed with its verdict."""
    out = {}
    for variant, by_space in scores.items():
        entry = {}
        for space, rows in by_space.items():
            entry[space] = {"psnr": _stats([r["psnr"] for r in rows]),
                            "gap": _stats([r["gap"] for r in rows]),
                            "ceiling": rows[0]["ceiling"],
                            "per_seed": [[r["psnr"], r["gap"]] for r in rows]}
        if all(s in by_space for s in SPACES):
            diffs = [t["gap"] - v["gap"] for v, t in zip(by_space["vertices"], by_space["texels"])]
            mean, std = _stats(diffs)
            margin = max(2 * std, 0.2)
            entry["gap_change"] = {"diff_db": mean, "std_db": std, "margin_db": margin,
                                   "verdict": "smaller" if mean < -margin else "larger"
                                   if mean > margin else "tie"}
        out[variant] = entry
    return out


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "teacher_inputs"), metavar="DIR",
                    help="study_teacher_inputs.py's cache: captures and teachers")
    ap.add_argument("--teachers", default="paper,shading",
                    help=f"comma-separated, of {', '.join(T.VARIANTS)} [default: paper,shading]")
    ap.add_argument("--models", default="",
                    help=f"comma-separated, of {', '.join(MODELS)}: trained here (cpu preset) "
                    "and scored like the teachers [default: none]")
    ap.add_argument("--model-seeds", type=int, default=1)
    ap.add_argument("--students", default="",
                    help="comma-separated study_student_env.py variants also scored "
                    "(their cache: --student-work) [default: none]")
    ap.add_argument("--student-work", default=str(B.OUT / "student_env"), metavar="DIR")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--directions", type=int, default=24,
                    help="directions of the superposition check [default: 24]")
    args = ap.parse_args(argv)
    if args.quick:
        ap.error("no --quick: the teachers are converged cpu-preset runs")
    teachers = [v.strip() for v in args.teachers.split(",") if v.strip()]
    import study_student_env as E
    students = [v.strip() for v in args.students.split(",") if v.strip()]
    models = [v.strip() for v in args.models.split(",") if v.strip()]
    if any(m not in MODELS for m in models):
        ap.error(f"--models: use {', '.join(MODELS)}")
    bad = [v for v in students if v not in E.VARIANTS]
    if bad:
        ap.error(f"unknown student variant(s) {', '.join(bad)}; use {', '.join(E.VARIANTS)}")
    bad = [v for v in teachers if v not in T.VARIANTS]
    if bad or not teachers:
        ap.error(f"unknown teacher variant(s) {', '.join(bad)}; use {', '.join(T.VARIANTS)}")
    out = B.start(args, "study_env_truth.py")
    work = Path(args.work)

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    captures = {(v, sp): P._capture(work, log, stage=stage_of(v, sp))[0]
                for v in teachers for sp in SPACES}
    seeds = list(range(args.seeds))
    for v in teachers:                              # the teachers (cached)
        for s in seeds:
            T._run(work, captures[v, "vertices"], v, s, log)
    for sp in SPACES:
        captures["model", sp] = P._capture(work, log, stage=stage_of("", sp))[0]
    model_seeds = list(range(args.model_seeds))
    with ThreadPoolExecutor(max(1, args.workers)) as pool:
        list(pool.map(lambda job: run_model(work, captures["model", "vertices"], *job, log),
                      [(m, s) for m in models for s in model_seeds]))
    jobs = [(str(work), str(captures[v, sp]), v, s, sp) for v in teachers for s in seeds
            for sp in SPACES]
    jobs += [(str(work), str(captures["model", sp]), m, s, sp) for m in models
             for s in model_seeds for sp in SPACES]
    for v in students:       # students distill on the scale's own (32-LED) capture
        for sp in SPACES:
            captures["student", sp] = P._capture(work, log, stage=stage_of("", sp))[0]
    check = str(captures[teachers[0], "vertices"])
    student_jobs = [(args.student_work, str(work), str(captures["student", sp]), v, s, sp)
                    for v in students for s in seeds for sp in SPACES]
    with ProcessPoolExecutor(max(1, args.workers), mp_context=get_context("spawn")) as pool:
        stage_check = {sp: pool.submit(superposition, check, sp, args.directions)
                       for sp in SPACES}
        done = list(pool.map(score_env, *zip(*jobs)))
        graded = list(pool.map(score_student, *zip(*student_jobs))) if student_jobs else []
        stage_check = {sp: f.result() for sp, f in stage_check.items()}
    scores = {v: {sp: [] for sp in SPACES} for v in teachers + models}
    for (_, _, v, _, sp), r in zip(jobs, done):
        scores[v][sp].append(r)
    scores.update({f"student {v}": {sp: [] for sp in SPACES} for v in students})
    for (_, _, _, v, _, sp), r in zip(student_jobs, graded):
        scores[f"student {v}"][sp].append(r)
    import numpy as np
    record = {"command": B.run_command("study_env_truth.py",
                                       sys.argv[1:] if argv is None else argv),
              "machine": limits, "seeds": seeds, "far_m": FAR, "models": models,
              "model_seeds": model_seeds,
              "wall_s": round(time.perf_counter() - t0, 1),
              "captures": {f"{v}/{sp}": Path(c).name for (v, sp), c in captures.items()},
              "superposition": {sp: {"median": float(np.median(r)), "mean": float(np.mean(r)),
                                     "max": float(np.max(r)), "directions": len(r)}
                                for sp, r in stage_check.items()},
              "results": summarize(scores)}
    P.B_write(out / "env_truth.json", record)
    (out / "env_truth.md").write_text(_markdown(record))
    print((out / "env_truth.md").read_text())


def _markdown(record: dict) -> str:
    sup = record["superposition"]
    lines = ["# The teachers' env-map gap against env renders integrated at vertices or at "
             "texels", "",
             f"Command: `{record['command']}`  ",
             B.machine_line(record["machine"]) + "  ",
             f"Wall time: {record['wall_s'] / 60:.1f} min for this invocation (the teachers "
             f"were trained by study_teacher_inputs.py); seeds "
             f"{', '.join(map(str, record['seeds']))}; right hand, `converged` capture, "
             f"`--preset cpu` OLAT teachers; the env split: every held-out env render.", "",
             "**The stage alone.** One direction of an env map against an LED "
             f"{record['far_m']:.0f} m away in that direction, relative MSE over camera 0 "
             "at held-out pose 0:", "",
             "| env_space | median | mean | max | directions |", "|---|---|---|---|---|"]
    for sp, r in sup.items():
        lines.append(f"| {sp} | {100 * r['median']:.2f} % | {100 * r['mean']:.2f} % | "
                     f"{100 * r['max']:.2f} % | {r['directions']} |")
    lines += ["", "**The teachers** (and the students of study_student_env.py, `student …`, "
              "each distilled from its seed's teacher on the 32-LED capture), env-map PSNR "
              "against the ground truth and gap to the ceiling (dB, mean ± std over seeds), "
              "scored on the capture's env renders at each `eval_env_space`:", "",
              "| teacher | vertices: PSNR | gap | texels: PSNR | gap | gap change, paired "
              "(verdict: max(2σ, 0.2 dB)) |", "|---|---|---|---|---|---|"]
    for v, e in record["results"].items():
        cells = []
        for sp in SPACES:
            s = e.get(sp)
            cells += ([f"{s['psnr'][0]:.2f} ± {s['psnr'][1]:.2f}",
                       f"{s['gap'][0]:.2f} ± {s['gap'][1]:.2f}"] if s else ["—", "—"])
        ch = e.get("gap_change")
        lines.append(f"| {v} | " + " | ".join(cells) + " | "
                     + (f"{ch['diff_db']:+.2f} ± {ch['std_db']:.2f} → **{ch['verdict']}**"
                        if ch else "—") + " |")
    ceil = {sp: next((e[sp]["ceiling"] for e in record["results"].values() if e.get(sp)), None)
            for sp in SPACES}
    if record.get("models"):
        lines += ["", f"{', '.join(record['models'])}: `relight train-teacher CAPTURE --preset "
                  f"cpu --model M`, trained here on the 32-LED capture, seed(s) "
                  f"{', '.join(map(str, record['model_seeds']))} (± 0 with one seed: no "
                  f"spread, so a gap change needs 0.2 dB)."]
    lines += ["", "Ceilings (the perfect texture through the same compositing): "
              + ", ".join(f"{sp} {c:.2f} dB" for sp, c in ceil.items() if c is not None)
              + ". Captures: " + ", ".join(f"{k} `{c}`" for k, c in record["captures"].items())
              + " (the same LED frames: `eval_env_space` changes only the env renders).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
