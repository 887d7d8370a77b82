"""The ``cpu`` presets against their ceilings: one model per preset, trained as a user would.

For each learned model (``olat`` teacher, ``ggx`` baseline, URHand's ``linear`` model, the
``student`` and ``dram`` distilled from the olat teacher) this runs the command a user
runs — ``relight train-teacher CAPTURE --preset cpu`` / ``relight distill TEACHER
CAPTURE --preset cpu`` — with ``--metrics-out``, on the study's ``converged`` capture
(``benchmarks/studies/scales.json``), and reads back the validation curve: held-out
PSNR per validation step, the ceiling (the perfect texture through the same compositing
and pixel sampling, :mod:`relight_cli.neural.evaluate`) and the gap to it.  A row is
*converged* when its held-out PSNR gained < 0.2 dB over the last 20 % of iterations; it
*meets the preset's goal* when its final gap is ≤ 1 dB.  Wall time is the command's own
(subprocess, OMP threads as given), measured here: the outputs hold no timings.

Every finished run is cached under ``--work`` (capture, checkpoint, metrics, wall time),
so an interrupted run continues where it stopped; ``--models`` picks a subset.  Writes
``presets.{md,json,png}`` to ``--out``.  ``--quick`` (``make benchmarks QUICK=1``) is a
smoke run of the machinery: the tiny preset on the tiny study capture, olat, ggx and
linear only.  Run (hours on 2 CPU cores for all five)::

    .venv/bin/python benchmarks/bench_presets.py --work benchmarks/out/presets \\
        --out benchmarks/results [--models olat,ggx] [--threads 2]
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

HERE = Path(__file__).resolve().parent
RELIGHT = str(Path(sys.executable).parent / "relight")
MODELS = ("olat", "ggx", "linear", "student", "dram")
CONVERGED_DB, TAIL, GOAL_DB = 0.2, 0.2, 1.0


def _capture(work: Path, log, scale: str = "converged", stage: dict | None = None) -> Path:
    """The study scale's right-hand capture (made once); ``stage`` overrides some of the
    scale's capture settings (e.g. ``{"lights": 128}``: another capture, its own key)."""
    sys.path.insert(0, str(HERE))
    import study_hands as S
    settings = json.loads((HERE / "studies" / "scales.json").read_text())[scale]
    settings["capture"].update(stage or {})
    envs = S.env_specs()
    key = S.digest({"capture": settings["capture"], "eval": envs["eval"],
                    "v": S.CAPTURE_VERSION})
    folder = work / f"capture-{key}"
    if not (folder / "capture.json").is_file():
        log(f"making the capture {folder}")
        S.synth_capture(folder, *S.HANDS["right"], settings["capture"], envs["eval"])
    return folder, envs


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
    B_write(done, record)
    return record


def B_write(path: Path, obj) -> None:
    from relight_cli.provenance import write_text_atomic
    write_text_atomic(str(path), json.dumps(obj, indent=1) + "\n")


def _curve(record: dict, split: str = "heldout") -> list:
    return [[h["step"], h[split]["psnr"]] for h in record["metrics"]["details"]["history"]
            if isinstance(h.get(split), dict)]


def _row(model: str, record: dict) -> dict:
    final = record["metrics"]["metrics"]["heldout"]
    curve = _curve(record)
    iters = curve[-1][0]
    start = [v for s, v in curve if (1 - TAIL) * iters <= s < iters]
    gain = curve[-1][1] - start[0] if start else None
    return {"model": model, "iters": iters, "wall_s": record["wall_s"],
            "psnr": final["psnr"], "ceiling": final.get("ceiling", {}).get("psnr"),
            "gap": final.get("gap_to_ceiling"), "gain_tail_db": gain,
            "converged": None if gain is None else gain < CONVERGED_DB, "curve": curve}


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "presets"), metavar="DIR",
                    help="cache: the capture, checkpoints, metrics [default: benchmarks/out/presets]")
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    out = B.start(args, "bench_presets.py")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    unknown = [m for m in models if m not in MODELS]
    if unknown:
        ap.error(f"unknown model(s) {', '.join(unknown)}; use {', '.join(MODELS)}")

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    # --quick: a smoke run of the machinery (the tiny preset on the tiny study capture,
    # the three teacher-kind models: a minute or two), never a measurement of the presets
    preset = "tiny" if args.quick else "cpu"
    if args.quick:
        work = work / "quick"
        work.mkdir(parents=True, exist_ok=True)
        models = [m for m in models if m in ("olat", "ggx", "linear")]
    capture, envs = _capture(work, log, "tiny" if args.quick else "converged")
    train = [a for e in envs["train"] for a in ("--envs", e)]
    held = [a for e in envs["eval"] for a in ("--eval-envs", e)]
    rows = []
    for model in models:
        if model in ("olat", "ggx", "linear"):
            cmd = ["train-teacher", capture, "--preset", preset, "--model", model]
        else:
            teacher = work / "olat.pt"
            if not teacher.is_file():
                _run("olat", ["train-teacher", capture, "--preset", preset, "--model", "olat",
                              "-o", teacher, "--metrics-out", work / "olat.json", "-q"],
                     work, args.threads, log)
            cmd = ["distill", teacher, capture, *train, *held, "--preset", preset,
                   "--student", model]
        cmd += ["-o", work / f"{model}.pt", "--metrics-out", work / f"{model}.json", "-q"]
        rows.append(_row(model, _run(model, cmd, work, args.threads, log)))
    wall = time.perf_counter() - t0
    record = {"command": B.run_command("bench_presets.py", sys.argv[1:] if argv is None else argv),
              "machine": limits, "threads": args.threads, "capture": str(capture),
              "preset": preset, "quick": bool(args.quick),
              "wall_s": round(wall, 1), "rows": rows}
    B_write(out / "presets.json", record)
    (out / "presets.md").write_text(_markdown(record))
    _plot(record, out / "presets.png")
    print((out / "presets.md").read_text())


def _markdown(record: dict) -> str:
    lines = [f"# The `{record['preset']}` presets against their ceilings", "",
             f"Made by `{record['command']}`"
             + (" (`--quick`: a smoke run of the tiny preset, not a measurement)"
                if record["quick"] else "")
             + f"; {record['wall_s'] / 60:.1f} min of wall time "
             f"(finished runs are cached and cost nothing).", "",
             B.machine_line(record["machine"]), "",
             "| model | iterations | wall (min) | held-out PSNR | ceiling | gap (dB) | gain over "
             "last 20 % (dB) | converged | within 1 dB |", "|---|---|---|---|---|---|---|---|---|"]
    for r in record["rows"]:
        gap = r["gap"]
        lines.append(
            f"| {r['model']} | {r['iters']} | {r['wall_s'] / 60:.1f} | {r['psnr']:.2f} | "
            + (f"{r['ceiling']:.2f}" if r["ceiling"] is not None else "—") + " | "
            + (f"{gap:+.2f}" if gap is not None else "—") + " | "
            + (f"{r['gain_tail_db']:+.2f}" if r["gain_tail_db"] is not None else "—") + " | "
            + {True: "yes", False: "no", None: "—"}[r["converged"]] + " | "
            + ("—" if gap is None else "yes" if gap <= GOAL_DB else "no") + " |")
    lines += ["", "Held-out poses of the capture (the preset's `val_samples`: 16 for `cpu`), "
              "masked by the ground-truth hand "
              "mask. Ceiling: the stage's own shader at the model's texel centres through "
              "the same compositing and pixel sampling (not a strict bound: a texture fitted "
              "through the bilinear lookup can beat it). Plot: presets.png.", ""]
    return "\n".join(lines)


def _plot(record: dict, path: Path) -> None:
    fig, (ax,) = B.figure()
    for r in record["rows"]:
        steps = [p[0] for p in r["curve"]]
        line, = ax.plot(steps, [p[1] for p in r["curve"]], marker="o", label=r["model"])
        if r["ceiling"] is not None:
            ax.axhline(r["ceiling"], color=line.get_color(), linestyle=":", linewidth=1)
    ax.set_xlabel("iteration")
    ax.set_ylabel("held-out PSNR (dB); dotted: ceiling")
    ax.set_title(f"{record['preset']} presets: held-out PSNR against iterations")
    ax.grid(True, alpha=0.3)
    ax.legend()
    B.save(fig, path, record["machine"])


if __name__ == "__main__":
    main()
