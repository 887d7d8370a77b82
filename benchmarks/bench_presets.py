"""The ``cpu`` presets against their ceilings: one model per preset, trained as a user would.

For each learned model (``olat`` teacher, ``ggx`` baseline, URHand's ``linear`` model, the
``student`` and ``dram`` distilled from the olat teacher) this runs the command a user
runs — ``relight train-teacher CAPTURE --preset cpu`` / ``relight distill TEACHER
CAPTURE --preset cpu`` — with ``--metrics-out``, on the study's ``converged`` capture
(``benchmarks/studies/scales.json``) with its env maps rendered as the stage shades its
LEDs (``--eval-env-space texels``, synth-capture's default), and reads back the scores and
the validation curve.  A teacher is judged on every sample of its held-out LED frames and
also scored under the held-out env maps; a student renders env maps only and is judged
there, against the ground truth, where its gap includes its teacher's own error (the olat
row's env gap, same renders).  Each score comes with the ceiling (the perfect texture
through the same compositing and pixel sampling, :mod:`relight_cli.neural.evaluate`) and
the gap to it.  A row is *converged* when its validation curve gained < 0.2 dB over the
last 20 % of iterations; it *meets the preset's goal* when its gap is ≤ 1 dB (both rules
are :mod:`relight_cli.neural.judging`'s).  Wall time
is the command's own (subprocess, ``--threads`` torch threads, ``--workers`` models at
once), measured here: the outputs hold no timings.

Every finished run is cached under ``--work`` (capture, checkpoint, metrics, wall time),
so an interrupted run continues where it stopped; ``--models`` picks a subset.  Writes
``presets.{md,json,png}`` to ``--out``.  ``--quick`` (``make benchmarks QUICK=1``) is a
smoke run of the machinery: the tiny preset on the tiny study capture.  Run (28.5 min
on 2 CPU cores for all five, two at a time on one thread each, measured)::

    .venv/bin/python benchmarks/bench_presets.py --work benchmarks/out/presets \\
        --out benchmarks/results/converged/presets --threads 1 --workers 2 [--models olat,ggx]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
from relight_cli.neural import judging as J  # noqa: E402

HERE = Path(__file__).resolve().parent
RELIGHT = str(Path(sys.executable).parent / "relight")
MODELS = ("olat", "ggx", "linear", "student", "dram")
#: the tail a run's convergence is read over (DESIGN.md's "converged": the library's rule,
#: :mod:`relight_cli.neural.judging`, as is a preset's 1-dB goal)
TAIL = J.CONVERGED_TAIL


def _run(name: str, argv: list, work: Path, threads: int, log) -> dict:
    """Run one command once (cached): {"metrics": the validation record, "wall_s"}."""
    done = work / f"{name}.done.json"
    if done.is_file():
        return json.loads(done.read_text())
    log(f"{name}: {' '.join(map(str, argv))}")
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    t0 = time.perf_counter()
    r = subprocess.run([RELIGHT, *map(str, argv)], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"bench_presets.py: error: {name} failed:\n{r.stderr[-2000:]}")
    record = {"argv": [str(a) for a in argv], "wall_s": round(wall, 1),
              "metrics": json.loads((work / f"{name}.json").read_text())}
    B.write_json(done, record, ensure_ascii=True)
    return record


TEACHERS = ("olat", "ggx", "linear")


def _curve(record: dict, split: str) -> list:
    return [[h["step"], h[split]["psnr"]] for h in record["metrics"]["details"]["history"]
            if isinstance(h.get(split), dict)]


def _split(scores: dict | None) -> dict | None:
    """``{"psnr", "ceiling", "gap", "samples"}`` of one scored split (None: not scored)."""
    if not isinstance(scores, dict) or "psnr" not in scores:
        return None
    return {"psnr": scores["psnr"], "ceiling": scores.get("ceiling", {}).get("psnr"),
            "gap": scores.get("gap_to_ceiling"), "samples": scores.get("samples")}


def _row(model: str, record: dict) -> dict:
    """One model's standing.  A teacher is judged on its held-out LED frames, *every*
    sample of them (``heldout_all``; the 16 its validation curve scores can mislead by
    more than a dB), and also scored under the capture's held-out env maps; a student
    renders env maps only: held-out poses under held-out maps against the ground truth
    (``vs_ground_truth``) and against its teacher (``vs_teacher``).  ``goal``: the split
    the preset's 1-dB goal is read on; ``curve``: the validation curve that says whether
    the run converged (< 0.2 dB over its last 20 % of iterations)."""
    m = record["metrics"]["metrics"]
    if model in TEACHERS:
        goal, env, curve = _split(m.get("heldout_all") or m["heldout"]), _split(m.get("env")), \
            _curve(record, "heldout")
        teacher, along = None, _split(m["heldout"])
    else:
        # a capture without env renders (--quick's): against the teacher only
        goal = env = _split(m.get("vs_ground_truth"))
        teacher = m["vs_teacher"]["psnr"]
        curve = _curve(record, "vs_ground_truth" if goal else "vs_teacher")
        along = goal
    iters = curve[-1][0]
    # the last 20 %, or the last validation interval where validations are sparser
    gain, tail_from = J.tail_gain(curve, iters, metric="psnr", last_interval=True)
    return {"model": model, "iters": iters, "wall_s": record["wall_s"],
            "tail_from": tail_from,
            "goal_split": "heldout_all" if model in TEACHERS else "env", "goal": goal,
            "env": env, "vs_teacher_psnr": teacher, "gain_tail_db": gain,
            "converged": J.converged([gain]), "curve": curve,
            "curve_ceiling": along["ceiling"] if along else None}


def _commands(models: list, work: Path, capture: Path, envs: dict, preset: str) -> dict:
    """``{model: argv}``, the command a user runs for it; the students distil the olat
    teacher this run trains (so ``olat`` is always among the commands they need)."""
    train = [a for e in envs["train"] for a in ("--envs", e)]
    held = [a for e in envs["eval"] for a in ("--eval-envs", e)]
    students = any(m not in TEACHERS for m in models)
    cmds = {}
    for model in (["olat"] if students or "olat" in models else []) + \
            [m for m in models if m != "olat"]:
        if model in TEACHERS:
            cmd = ["train-teacher", capture, "--preset", preset, "--model", model]
        else:
            cmd = ["distill", work / "olat.pt", capture, *train, *held, "--preset", preset,
                   "--student", model]
        cmds[model] = cmd + ["-o", work / f"{model}.pt", "--metrics-out",
                             work / f"{model}.json", "-q"]
    return cmds


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "presets"), metavar="DIR",
                    help="cache: the capture, checkpoints, metrics [default: benchmarks/out/presets]")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--threads", type=B.integer(1), default=2,
                    help="torch threads per model's process")
    ap.add_argument("--workers", type=B.integer(1), default=1,
                    help="models trained at once, each its own process (the students start "
                         "once the olat teacher is trained) [default: 1]")
    ap.add_argument("--ggx-shadowing", choices=("smith", "schlick"), default="smith",
                    help="the capture's GGX lobe (synth-capture --ggx-shadowing): smith, "
                         "synth-capture's default, or schlick, the stage of the captures made "
                         "before issue 50 (results/converged/presets/) [default: smith]")
    args = ap.parse_args(argv)
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    unknown = [m for m in models if m not in MODELS]
    if unknown or not models:
        ap.error(f"unknown model(s) {', '.join(unknown) or '(none named)'}; "
                 f"use {', '.join(MODELS)}")
    out = B.start(args, "bench_presets.py", {"--work": args.work})
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    # --quick: a smoke run of the machinery (the tiny preset on the tiny study capture:
    # a few minutes), never a measurement of the presets
    preset = "tiny" if args.quick else "cpu"
    if args.quick:
        work = work / "quick"
        work.mkdir(parents=True, exist_ok=True)
    # env renders shaded as the stage shades its LEDs: synth-capture's default
    capture, envs = B.study_capture(work, log, "tiny" if args.quick else "converged",
                                    stage={"eval_env_space": "texels",
                                           "ggx_shadowing": args.ggx_shadowing})
    cmds = _commands(models, work, capture, envs, preset)
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(args.workers) as pool:
        runs = {}

        def job(name, after):
            if after is not None:
                after.result()          # the students wait for their teacher
            return _run(name, cmds[name], work, args.threads, log)

        for name in cmds:             # olat first: a worker never waits on a queued job
            runs[name] = pool.submit(job, name, runs["olat"] if name not in TEACHERS else None)
        rows = [_row(m, runs[m].result()) for m in MODELS if m in models]
    wall = time.perf_counter() - t0
    record = {"command": B.run_command("bench_presets.py", sys.argv[1:] if argv is None else argv),
              "machine": limits, "threads": args.threads, "workers": args.workers,
              "capture": str(capture), "preset": preset, "quick": bool(args.quick),
              "wall_s": round(wall, 1), "rows": rows}
    B.write_json(out / "presets.json", record, ensure_ascii=True)
    (out / "presets.md").write_text(_markdown(record))
    _plot(record, out / "presets.png")
    print((out / "presets.md").read_text())


def _cells(s: dict | None) -> str:
    if s is None:
        return "— | — | —"
    return (f"{s['psnr']:.2f} | " + (f"{s['ceiling']:.2f}" if s["ceiling"] is not None else "—")
            + " | " + (f"{s['gap']:+.2f}" if s["gap"] is not None else "—"))


def _markdown(record: dict) -> str:
    lines = [f"# The `{record['preset']}` presets against their ceilings", "",
             f"Made by `{record['command']}`"
             + (" (`--quick`: a smoke run of the tiny preset, not a measurement)"
                if record["quick"] else "")
             + f"; {record['wall_s'] / 60:.1f} min of wall time "
             f"(finished runs are cached and cost nothing). Each model is the command a "
             f"user runs, its own process on {record['threads']} thread(s), "
             f"{record.get('workers', 1)} at a time.", "",
             B.machine_line(record["machine"]), "",
             "| model | iterations | wall (min) | held-out LED frames: PSNR | ceiling | gap "
             "(dB) | env maps: PSNR | ceiling | gap (dB) | student against its teacher: PSNR "
             "| gain over last 20 % (dB) | converged | within 1 dB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in record["rows"]:
        led = r["goal"] if r["goal_split"] == "heldout_all" else None
        gap = r["goal"]["gap"] if r["goal"] else None
        lines.append(
            f"| {r['model']} | {r['iters']} | {r['wall_s'] / 60:.1f} | {_cells(led)} | "
            f"{_cells(r['env'])} | "
            + (f"{r['vs_teacher_psnr']:.2f}" if r["vs_teacher_psnr"] is not None else "—")
            + " | " + (f"{r['gain_tail_db']:+.2f}" if r["gain_tail_db"] is not None else "—")
            + (f" (from {r['tail_from']})" if r.get("tail_from") is not None
               and r["tail_from"] < (1 - TAIL) * r["iters"] else "") + " | "
            + {True: "yes", False: "no", None: "—"}[r["converged"]] + " | "
            + {True: "yes", False: "no", None: "—"}[J.within_goal(gap)]
            + (" (env)" if r["goal_split"] == "env" else "") + " |")
    olat = next((r for r in record["rows"] if r["model"] == "olat"), None)
    lines += ["", "Held-out LED frames: every sample of the capture's held-out poses "
              "(grouped lights). Env maps: its held-out poses under its held-out env maps, "
              "against renders shaded as the stage shades its LEDs (`synth-capture "
              "--eval-env-space texels`, the default); the students are judged there (they "
              "render env maps only) and their gap includes their teacher's own error under "
              "the same renders (the olat row's env gap)"
              + (":" if olat and olat["env"] else "."), ""]
    if olat and olat["env"] and olat["env"]["gap"] is not None:
        for r in record["rows"]:
            if r["goal_split"] == "env" and r["env"] and r["env"]["gap"] is not None:
                lines.append(f"- {r['model']}: {r['env']['gap']:.2f} dB below the ceiling, "
                             f"{olat['env']['gap']:.2f} of it the teacher's, "
                             f"{r['env']['gap'] - olat['env']['gap']:.2f} its own (against "
                             f"its teacher: {r['vs_teacher_psnr']:.2f} dB)")
        lines.append("")
    lines += ["Masked by the ground-truth hand mask. Ceiling: the stage's own shader at the "
              "model's texel centres through the same compositing and pixel sampling (not a "
              "strict bound: a texture fitted through the bilinear lookup can beat it). "
              "Converged: the validation curve (a teacher's 16 held-out samples, a student's "
              "env renders) gained < 0.2 dB over the last 20 % of iterations (over the last "
              "validation interval, from the iteration shown, where validations are "
              "sparser). "
              "Plot: presets.png.", ""]
    return "\n".join(lines)


def _plot(record: dict, path: Path) -> None:
    fig, (ax,) = B.figure()
    for r in record["rows"]:
        steps = [p[0] for p in r["curve"]]
        label = r["model"] + (" (env maps)" if r["goal_split"] == "env" else "")
        line, = ax.plot(steps, [p[1] for p in r["curve"]], marker="o", label=label)
        if r.get("curve_ceiling") is not None:    # the ceiling of the curve's own samples
            ax.axhline(r["curve_ceiling"], color=line.get_color(), linestyle=":",
                       linewidth=1)
    ax.set_xlabel("iteration")
    ax.set_ylabel("validation PSNR (dB); dotted: ceiling")
    ax.set_title(f"{record['preset']} presets: validation PSNR against iterations")
    ax.grid(True, alpha=0.3)
    ax.legend()
    B.save(fig, path, record["machine"])


if __name__ == "__main__":
    B.run_main("bench_presets.py", main)
