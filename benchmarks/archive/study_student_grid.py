"""The converged student rendered on other env grids than it trained on: error against
render time, and where the student's gap to its ceiling comes from.

At the ``cpu`` preset a student distills on an 8×16 env grid (``env_res``): its teacher's
pseudo ground truth Σ_m b_m C_m costs one teacher pass per grid direction and (pose,
camera), 4× less than on the paper's 16×32.  Its inputs, though, are physically based
features — diffuse and Phong integrals over the sphere with traced visibility
(RelightableHands Sec. 4.2) — that any grid approximates, better the finer it is.  So
the same checkpoint can render on a finer grid than it trained on (``render_env_res``).
This measures what that gives, on the study_student_env.py students (its cache,
``--students``) against the stage's consistent ground truth (``eval_env_space: texels``,
study_env_truth.py), held-out poses × held-out env maps, every env render:

* each student on each ``--grids`` grid: PSNR and gap to the ceiling (the perfect
  texture at the student's N through the same compositing), and the render time of one
  frame on that grid (visibility traced for the pose, features, decoder, compositing:
  ``relight --model student``'s work), median over the renders of seed 0;
* each seed's teacher under the same renders on 8×16 (the student's target) and 16×32
  (the paper's grid), so the student's gap splits into

      ceiling − student(R) = (ceiling − teacher 16×32)       the teacher's own error
                           + (teacher 16×32 − teacher 8×16)  the 8×16 grid's cost
                           + (teacher 8×16 − student 8×16)   distillation
                           − (student R − student 8×16)      rendering on grid R

A difference is a verdict only when it exceeds max(2 σ over seeds, 0.2 dB), paired by
seed.  Trains nothing; scores are cached beside the students.  Writes
``student_grid.{md,json,png}`` to ``--out``.  Run (about 10 min on 2 cores)::

    .venv/bin/python benchmarks/study_student_grid.py --seeds 3 --workers 2 \\
        --variants tied,linear,linear_8k,linear_tshading \\
        --out benchmarks/results/converged/student_grid
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
import bench_presets as P  # noqa: E402

#: the teacher's pseudo ground truth on these grids (the student's and the paper's)
TEACHER_GRIDS = ((8, 16), (16, 32))


def _grid(text: str) -> tuple:
    h, w = (int(v) for v in text.lower().split("x"))
    return h, w


def _name(grid) -> str:
    return f"{grid[0]}x{grid[1]}"


def score_teacher(teachers: str, students: str, capture: str, teacher: str, seed: int,
                  grid) -> dict:
    """The teacher ``teacher``_s``seed``'s pseudo ground truth on ``grid`` against every env
    render of ``capture`` (cached beside the students): {psnr, samples}."""
    path = Path(students) / f"teacher_{teacher}_s{seed}.target_{_name(grid)}.texels.json"
    if path.is_file():
        return json.loads(path.read_text())
    import numpy as np
    import torch

    import study_student_env as E
    from relight_cli.envmap import discretize_env
    from relight_cli.neural import distill as DI
    torch.set_num_threads(1)
    data, targets = E._targets(str(Path(teachers) / f"{teacher}_s{seed}.pt"), capture, None,
                               grid)
    rows = []
    for render in data.splits()["env"]:
        pose, env_name, camera, gt, mask = data.env_target(render[1])
        denv = discretize_env(data.env_map(env_name), *grid)
        m = DI._metrics(targets.image(pose, camera.name, denv, held_out=True).numpy(), gt, mask)
        if m:
            rows.append(m)
    out = {"psnr": float(np.mean([r["psnr"] for r in rows])), "samples": len(rows)}
    P.B_write(path, out)
    return out


def render_seconds(students: str, capture: str, variant: str, grid) -> float:
    """Median seconds of one student frame on ``grid`` (seed 0; every env render's pose
    and camera, visibility traced afresh for each as ``relight --model student`` does)."""
    import numpy as np
    import torch

    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.neural import distill as DI
    from relight_cli.neural.checkpoints import student_model
    from relight_cli.neural.data import CaptureData
    from relight_cli.neural.teacher import composite
    torch.set_num_threads(1)
    net, config = student_model(read_checkpoint(str(Path(students) / f"{variant}_s0.pt"),
                                                kind="student"))
    net.eval()
    data = CaptureData(capture, config.tex_res)
    times = []
    for render in data.splits()["env"]:
        pose, env_name, camera, gt, mask = data.env_target(render[1])
        denv = discretize_env(data.env_map(env_name), *grid)
        hand = data.eval_hand
        gb = data.gbuffer(pose, camera, held_out=True)
        t0 = time.perf_counter()
        features = DI.StudentFeatures(config, cache=1, env_res=grid)
        maps = features.maps(features.pose(hand, pose), denv, camera.center)
        with torch.no_grad():
            textures = DI.student_forward(net, config, maps, DI.hand_poses(hand, pose), denv,
                                          DI.wrist_rotations(hand, pose), "cpu")
            composite(textures, gb)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _stats(values) -> list:
    import numpy as np
    v = np.asarray(values, float)
    return [float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0]


def _verdict(diffs) -> dict:
    mean, std = _stats(diffs)
    margin = max(2 * std, 0.2)
    return {"diff_db": mean, "std_db": std, "margin_db": margin,
            "verdict": "better" if mean > margin else "worse" if mean < -margin else "tie"}


def summarize(students: dict, teachers: dict, grids: list, teacher_of: dict) -> dict:
    """students[variant][grid] = per-seed {psnr, ceiling, gap}; teachers[teacher][grid] =
    per-seed {psnr} → per variant: each grid's PSNR/gap (mean ± std), each grid against the
    training grid (paired), and the split of the gap on its best grid."""
    out = {}
    for v, by_grid in students.items():
        train = grids[0]
        entry = {"grids": {}, "teacher": teacher_of[v]}
        for g in grids:
            rows = by_grid[g]
            entry["grids"][g] = {"psnr": _stats([r["psnr"] for r in rows]),
                                 "gap": _stats([r["gap"] for r in rows]),
                                 "per_seed": [r["psnr"] for r in rows]}
            if g != train:
                entry["grids"][g]["vs_train"] = _verdict(
                    [a["psnr"] - b["psnr"] for a, b in zip(rows, by_grid[train])])
        t = teachers[teacher_of[v]]
        ceiling = by_grid[train][0]["ceiling"]
        best = max(grids, key=lambda g: entry["grids"][g]["psnr"][0])
        parts = []
        for i in range(len(by_grid[train])):
            fine, coarse = t["16x32"][i]["psnr"], t["8x16"][i]["psnr"]
            s_train, s_best = by_grid[train][i]["psnr"], by_grid[best][i]["psnr"]
            parts.append({"teacher": ceiling - fine, "env_grid": fine - coarse,
                          "distillation": coarse - s_train, "render_grid": s_train - s_best,
                          "total": ceiling - s_best})
        entry["best_grid"] = best
        entry["split_db"] = {k: _stats([p[k] for p in parts]) for k in parts[0]}
        entry["ceiling"] = ceiling
        out[v] = entry
    return out


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--students", default=str(B.OUT / "student_env"), metavar="DIR",
                    help="study_student_env.py's cache (its students)")
    ap.add_argument("--teachers", default=str(B.OUT / "teacher_inputs"), metavar="DIR",
                    help="study_teacher_inputs.py's cache (teachers, captures)")
    ap.add_argument("--variants", default="tied,linear",
                    help="comma-separated study_student_env.py variants [default: tied,linear]")
    ap.add_argument("--grids", default="8x16,16x32,32x64",
                    help="env grids HxW the students render on, their training grid first "
                    "[default: 8x16,16x32,32x64]")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    if args.quick:
        ap.error("no --quick: the students are converged cpu-preset runs")
    import study_env_truth as T
    import study_student_env as E
    from relight_cli.neural.config import STUDENT_PRESETS
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in E.VARIANTS or E.VARIANTS[v].get("student") == "dram"]
    if bad or not variants:
        ap.error(f"unknown or DRAM variant(s) {', '.join(bad)} (DRAM renders on its training "
                 f"grid only); use {', '.join(v for v in E.VARIANTS if 'dram' not in v)}")
    try:
        grids = [_grid(g) for g in args.grids.split(",") if g.strip()]
    except ValueError:
        ap.error("--grids: HxW, comma-separated")
    train = tuple(STUDENT_PRESETS["cpu"]["env_res"])
    if not grids or grids[0] != train:
        ap.error(f"--grids: the students' training grid {_name(train)} comes first")
    out = B.start(args, "study_student_grid.py")

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    capture = str(P._capture(Path(args.teachers), log,
                             stage=T.stage_of("", "texels"))[0])
    seeds = list(range(args.seeds))
    teacher_of = {v: E.teacher_of(v) for v in variants}
    names = sorted(set(teacher_of.values()))
    s_jobs = [(args.students, args.teachers, capture, v, s, "texels",
               None if g == train else g) for v in variants for s in seeds for g in grids]
    t_jobs = [(args.teachers, args.students, capture, t, s, g) for t in names for s in seeds
              for g in TEACHER_GRIDS]
    with ProcessPoolExecutor(max(1, args.workers), mp_context=get_context("spawn")) as pool:
        s_done = list(pool.map(T.score_student, *zip(*s_jobs)))
        t_done = list(pool.map(score_teacher, *zip(*t_jobs)))
    # timing: one process at a time, nothing else of this study running
    seconds = {v: {_name(g): render_seconds(args.students, capture, v, g) for g in grids}
               for v in variants}
    students = {v: {_name(g): [] for g in grids} for v in variants}
    for job, r in zip(s_jobs, s_done):
        students[job[3]][_name(job[6] or train)].append(r)
    teachers = {t: {_name(g): [] for g in TEACHER_GRIDS} for t in names}
    for job, r in zip(t_jobs, t_done):
        teachers[job[3]][_name(job[5])].append(r)
    record = {"command": B.run_command("study_student_grid.py",
                                       sys.argv[1:] if argv is None else argv),
              "machine": limits, "seeds": seeds, "grids": [_name(g) for g in grids],
              "wall_s": round(time.perf_counter() - t0, 1), "capture": Path(capture).name,
              "configs": {v: E.VARIANTS[v] for v in variants},
              "teachers": {t: {g: [r["psnr"] for r in rows] for g, rows in by.items()}
                           for t, by in teachers.items()},
              "render_s": seconds,
              "results": summarize(students, teachers, [_name(g) for g in grids], teacher_of)}
    P.B_write(out / "student_grid.json", record)
    (out / "student_grid.md").write_text(_markdown(record))
    _plot(record, out / "student_grid.png")
    print((out / "student_grid.md").read_text())


def _markdown(record: dict) -> str:
    grids = record["grids"]
    lines = ["# The converged student on other env grids than it trained on", "",
             f"Command: `{record['command']}`  ", B.machine_line(record["machine"]) + "  ",
             f"Wall time: {record['wall_s'] / 60:.1f} min for this invocation (scores in its "
             f"cache cost nothing; it trains nothing); seeds "
             f"{', '.join(map(str, record['seeds']))}; right hand, `converged` capture with "
             f"consistent env truth (`eval_env_space: texels`, `{record['capture']}`), "
             f"`--preset cpu` students of study_student_env.py, trained on {grids[0]}.", "",
             "Against the stage's ground truth, held-out poses × held-out env maps (every env "
             "render), PSNR (dB, mean ± std over seeds) with its gap to the ceiling, when the "
             "student's features are baked on each grid; render time: one frame "
             "(visibility traced, features, decoder, compositing), median over the renders "
             "of seed 0, one thread:", "",
             "| variant | " + " | ".join(f"{g}: PSNR | gap | s/frame" for g in grids)
             + " |", "|---|" + "---|---|---|" * len(grids)]
    for v, e in record["results"].items():
        cells = []
        for g in grids:
            s = e["grids"][g]
            cells += [f"{s['psnr'][0]:.2f} ± {s['psnr'][1]:.2f}",
                      f"{s['gap'][0]:.2f}", f"{record['render_s'][v][g]:.2f}"]
        lines.append(f"| {v} | " + " | ".join(cells) + " |")
    lines += ["", "Each grid against the training grid, paired by seed (verdict when "
              "|difference| > max(2 σ, 0.2 dB)):", ""]
    for v, e in record["results"].items():
        parts = []
        for g in grids[1:]:
            c = e["grids"][g]["vs_train"]
            parts.append(f"{g} {c['diff_db']:+.2f} ± {c['std_db']:.2f} dB → **{c['verdict']}**")
        lines.append(f"- {v} ({json.dumps(record['configs'][v])}): " + "; ".join(parts))
    lines += ["", "Where each student's gap on its best grid comes from (dB, mean ± std over "
              "seeds): its teacher's own error (ceiling − teacher on 16×32), the 8×16 grid's "
              "cost to the teacher's pseudo ground truth (teacher 16×32 − teacher 8×16), "
              "distillation (teacher 8×16 − student on 8×16), minus what rendering on the "
              "best grid recovers (student best − student 8×16):", "",
              "| variant | teacher | ceiling | teacher's error | 8×16 grid | distillation | "
              "render grid recovers | best grid | total gap |", "|---" * 9 + "|"]
    for v, e in record["results"].items():
        d = e["split_db"]

        def cell(k, sign=1.0):
            return f"{sign * d[k][0]:.2f} ± {d[k][1]:.2f}"
        lines.append(f"| {v} | {e['teacher']} | {e['ceiling']:.2f} | {cell('teacher')} | "
                     f"{cell('env_grid')} | {cell('distillation')} | "
                     f"{cell('render_grid', -1.0)} | {e['best_grid']} | {cell('total')} |")
    per_teacher = []
    for t, by in record["teachers"].items():
        per_teacher.append(f"{t}: " + ", ".join(f"{g} " + "/".join(f"{p:.2f}" for p in ps)
                                                for g, ps in by.items()))
    lines += ["", "Teachers' pseudo ground truth against the same renders (PSNR per seed): "
              + "; ".join(per_teacher) + ".",
              "", "Plot: student_grid.png (PSNR against render time per frame, one point per "
              "grid; the ceiling dashed).", ""]
    return "\n".join(lines)


def _plot(record: dict, path: Path) -> None:
    try:
        import matplotlib
    except ImportError:
        return
    matplotlib.use("Agg")
    fig, (ax,) = B.figure(width=8.4)
    grids = record["grids"]
    ceiling = None
    for i, (v, e) in enumerate(record["results"].items()):
        xs = [record["render_s"][v][g] for g in grids]
        ys = [e["grids"][g]["psnr"][0] for g in grids]
        err = [e["grids"][g]["psnr"][1] for g in grids]
        ax.errorbar(xs, ys, yerr=err, marker="o", capsize=3, label=v)
        if i == 0:                       # the grids' labels once (every variant's align)
            for x, y, g in zip(xs, ys, grids):
                ax.annotate(g, (x, y), textcoords="offset points", xytext=(4, -10),
                            fontsize=7)
        ceiling = e["ceiling"]
    if ceiling is not None:
        ax.axhline(ceiling, ls="--", color="k", lw=1, label="ceiling")
    for t, by in record["teachers"].items():
        mean = sum(by["16x32"]) / len(by["16x32"])
        ax.axhline(mean, ls=":", lw=1, color="0.4" if t == "paper" else "0.6",
                   label=f"teacher ({t} input) on 16x32")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per frame (one thread)")
    ax.set_ylabel("PSNR vs ground truth (dB)")
    ax.set_title("Students rendered on finer env grids than they trained on (8×16)",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    B.save(fig, path, record["machine"])


if __name__ == "__main__":
    main()
