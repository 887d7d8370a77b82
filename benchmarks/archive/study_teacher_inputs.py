"""What the OLAT teacher's per-texel input costs it: the paper's (light, view, visibility)
against the same plus the half vector, at the ``cpu`` preset, to convergence, over seeds.

The converged Table 1/3 (``results/converged/study_rh_t13.md``) left the OLAT teacher
3.2–4.8 dB below its ceiling while the GGX baseline, the same U-Net with an explicit
microfacet lobe, came within 0.7 dB.  Per image, the teacher's held-out error is not
spread evenly: a few (frame, camera) images 10–16 dB below the ceiling — point-light
highlights on the back of the hand and bright grazing rims, both specular — carry most of
the mean-PSNR gap, while most images sit within 1 dB of it (and several above: a texture
fitted through the bilinear lookup can beat point samples).  A microfacet lobe is a
function of one coordinate of the local half vector (h_z = n·h), which the paper's input
makes the network build from l and v through 3×3 convolutions; ``TeacherConfig.inputs =
half`` hands it h directly (:mod:`relight_cli.neural.models`).

Each run is the command a user runs, ``relight train-teacher CAPTURE --preset cpu --model
olat --config VARIANT.json --seed S`` (one thread each, ``--workers`` at a time), on the
study's ``converged`` right-hand capture (``studies/scales.json``), cached under
``--work`` so an interrupted study resumes.  A variant's difference from ``paper`` is a
verdict only when it exceeds max(2 σ over seeds, 0.2 dB) (the study_hands rule).
Writes ``teacher_inputs.{md,json,png}`` to ``--out``.  Run (about 9 min per run on one
core; 3 seeds × 2 variants, two at a time: ~30 min)::

    .venv/bin/python benchmarks/study_teacher_inputs.py --seeds 3 --workers 2 \\
        --work benchmarks/out/teacher_inputs --out benchmarks/results/converged
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
import bench_presets as P  # noqa: E402

VARIANTS = {"paper": {"inputs": "paper"}, "half": {"inputs": "half"},
            "code": {"inputs": "paper", "head": "code"},
            "shading": {"inputs": "shading"}, "nopose": {"inputs": "paper", "pose": "none"},
            "shading_l128": {"inputs": "shading"},
            # the cpu preset's teacher blind to the camera (``view: none``): is its
            # env-map error view-dependent error (study_teacher_directions.py)?
            "shading_noview": {"inputs": "shading", "view": "none"},
            # the cpu preset's teacher on captures whose hand moves through more key poses
            # in the same 96 frames: is its held-out error the capture's few poses?
            "shading_k3": {"inputs": "shading"}, "shading_k1": {"inputs": "shading"}}
#: variants trained on another capture: the converged scale's with these stage settings
#: overridden.  ``shading_l128``: 128 stage lights instead of 32, the same frames, groups
#: of 4 and cameras (so as many images, each light lit in 2 grouped frames instead of 8):
#: do the env maps' directions between the 32 lights cost the teacher its env-map gap?
#: The env renders (eval hand, env maps, cameras) are the same images on both stages;
#: the held-out and training frames are not (other lights), each scored with its own
#: ceiling.
#: ``shading_k3`` / ``shading_k1``: a random key pose every 3rd / every frame instead of
#: every 10th (``synth-capture --keyframe-every``): the same 96 frames, LEDs, groups and
#: cameras (so as many images), 24 / 72 key poses before the held-out segment instead of 8.
#: The env renders' held-out poses are drawn apart from the motion, so they are the same
#: poses; but the dome is framed on the whole motion (the cameras' focal lengths differ by
#: up to 7 %), so they are other images, judged like the rest on the gap to their own
#: ceiling.
STAGES = {"shading_l128": {"lights": 128}, "shading_k3": {"keyframe_every": 3},
          "shading_k1": {"keyframe_every": 1}}
SPLITS = ("heldout", "fully_lit", "env")
#: what a variant is, in the table's title
TITLES = {"half": "the half vector added", "code": "the authors' code's head",
          "shading": "the student's shading features added", "nopose": "no pose",
          "shading_l128": "the same on a 128-light stage",
          "shading_noview": "the same blind to the camera",
          "shading_k3": "the same on a capture with a key pose every 3rd frame",
          "shading_k1": "the same on a capture with a key pose every frame"}
#: held-out env-render poses of the converged scale's capture (studies/scales.json)
SCALE_EVAL_POSES = 2
#: what the table compares: every held-out sample, then the validation's splits
COMPARED = ("all_heldout", "all_train") + SPLITS + ("env_texels",)
#: ``env_texels``: every held-out env render of the converged capture made again with its
#: env renders shaded as its LEDs (the consistent truth, study_env_truth.py), the same
#: images for every variant, one of another stage too (a teacher's texture is scored
#: through any capture's cameras): compared on the PSNR itself
SAME_IMAGES = ("env_texels",)


def _run(work: Path, capture: Path, variant: str, seed: int, log) -> dict:
    """One training run (cached): {"argv", "wall_s", "metrics"}."""
    name = f"{variant}_s{seed}"
    done = work / f"{name}.done.json"
    if done.is_file():
        return json.loads(done.read_text())
    config = work / f"{variant}.json"
    P.B_write(config, VARIANTS[variant])
    argv = ["train-teacher", str(capture), "--preset", "cpu", "--model", "olat", "--config",
            str(config), "--seed", str(seed), "-o", str(work / f"{name}.pt"),
            "--metrics-out", str(work / f"{name}.json"), "-q"]
    return run_once(work, name, argv, "study_teacher_inputs.py", log)


def run_once(work: Path, name: str, argv: list, who: str, log) -> dict:
    """``relight ARGV`` on one thread, its record {"argv", "wall_s", "metrics" (the
    ``--metrics-out`` file work/NAME.json)} cached as work/NAME.done.json."""
    log(f"{name}: relight {' '.join(argv)}")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    r = subprocess.run([P.RELIGHT, *argv], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{who}: error: {name} failed:\n{r.stderr[-2000:]}")
    record = {"argv": argv, "wall_s": round(wall, 1),
              "metrics": json.loads((work / f"{name}.json").read_text())}
    P.B_write(work / f"{name}.done.json", record)
    log(f"{name}: done in {wall / 60:.1f} min")
    return record


def _score_all(work: Path, capture: Path, variant: str, seed: int) -> dict:
    """Every held-out and every training sample of the run's checkpoint scored with its
    ceiling (cached): the training command validates on ``val_samples`` (16) of each
    split only.  {"heldout": {psnr, mse, ssim, samples, ceiling, gap}, "train": ...}."""
    name = f"{variant}_s{seed}"
    path = work / f"{name}.all.json"
    if path.is_file():
        return json.loads(path.read_text())
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.neural.evaluate import evaluate_capture, load_hand_model
    model = load_hand_model(read_checkpoint(str(work / f"{name}.pt"), kind="teacher"),
                            name=name)
    scores = evaluate_capture(str(capture), [model], ["heldout", "train"])
    out = {split: {"psnr": s["psnr"], "mse": s["mse"], "ssim": s["ssim"],
                   "samples": s["samples"], "ceiling": s["ceiling"]["psnr"],
                   "gap": s["gap_to_ceiling"]}
           for split, s in scores.items()}
    P.B_write(path, out)
    return out


def _seed_row(record: dict, every: dict, consistent: dict | None = None) -> dict:
    m = record["metrics"]["metrics"]
    row = {"wall_s": record["wall_s"], "all_heldout": every["heldout"],
           "all_train": every["train"]}
    if consistent is not None:
        row["env_texels"] = {k: consistent[k] for k in ("psnr", "ceiling", "gap")}
    for split in SPLITS:
        s = m.get(split) or {}
        # (the validation's own samples: val_samples of each split)
        row[split] = {"psnr": s.get("psnr"), "ceiling": (s.get("ceiling") or {}).get("psnr"),
                      "gap": s.get("gap_to_ceiling"), "mse": s.get("mse")}
    curve = P._curve(record)
    iters = curve[-1][0]
    tail = [v for s, v in curve if (1 - P.TAIL) * iters <= s < iters]
    row["gain_tail_db"] = curve[-1][1] - tail[0] if tail else None
    row["curve"] = curve
    return row


def _stats(values: list) -> tuple:
    import numpy as np
    v = np.asarray(values, float)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else 0.0


def summarize(runs: dict, seeds: list, base: str = "paper") -> dict:
    """Per variant: per-seed rows, mean ± std of each split's PSNR and gap, convergence;
    per other variant and split: the mean paired difference from ``base`` and its
    verdict (stored as ``versus_paper`` whatever the base; the record names the base)."""
    out = {}
    for variant, rows in runs.items():
        entry = {"seeds": rows}
        for split in COMPARED:
            psnr = [r[split]["psnr"] for r in rows if (r.get(split) or {}).get("psnr")
                    is not None]
            gap = [r[split]["gap"] for r in rows if (r.get(split) or {}).get("gap")
                   is not None]
            if psnr:
                entry[split] = {"psnr": _stats(psnr), "gap": _stats(gap) if gap else None,
                                "ceiling": rows[0][split]["ceiling"]}
        gains = [r["gain_tail_db"] for r in rows]
        entry["converged"] = all(g is not None and g < P.CONVERGED_DB for g in gains)
        entry["wall_min"] = sum(r["wall_s"] for r in rows) / 60
        out[variant] = entry
    base_name, base = base, runs.get(base)
    for variant, rows in runs.items():
        if variant == base_name or base is None:
            continue
        out[variant]["versus_paper"] = {}
        # on another stage the frames are other images: compare the gaps to each one's
        # own ceiling (the env renders are the same images, so there it is the PSNR too)
        other = STAGES.get(variant) != STAGES.get(base_name)
        for split in COMPARED:
            key = "gap" if other and split not in SAME_IMAGES else "psnr"
            sign = -1.0 if key == "gap" else 1.0
            diffs = [sign * (a[split][key] - b[split][key]) for a, b in zip(rows, base)
                     if (a.get(split) or {}).get(key) is not None
                     and (b.get(split) or {}).get(key) is not None]
            if not diffs:
                continue
            mean, std = _stats(diffs)
            margin = max(2 * std, 0.2)
            verdict = "better" if mean > margin else "worse" if mean < -margin else "tie"
            out[variant]["versus_paper"][split] = {"diff_db": mean, "std_db": std,
                                                   "margin_db": margin, "verdict": verdict,
                                                   "on": key}
    return out


def parse_variants(ap, argv, known: dict, default: str, seeds: int, what: str):
    """``--variants`` (of ``known``), ``--seeds``, ``--workers`` added to ``ap`` and parsed:
    (args, the variants); no ``--quick`` (each run is a converged cpu-preset ``what``)."""
    ap.add_argument("--variants", default=default,
                    help=f"comma-separated, of {', '.join(known)} [default: {default}]")
    ap.add_argument("--seeds", type=int, default=seeds)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in known]
    if bad or not variants:
        ap.error(f"unknown variant(s) {', '.join(bad)}; use {', '.join(known)}")
    if args.quick:
        ap.error(f"no --quick: each run is a converged cpu-preset {what}")
    return args, variants


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "teacher_inputs"), metavar="DIR",
                    help="cache: the capture, checkpoints, metrics")
    ap.add_argument("--eval-poses", type=int, default=SCALE_EVAL_POSES, metavar="N",
                    help="held-out poses of the consistent-truth env renders (a capture of "
                    "its own, other images than the converged capture's) [default: 2]")
    ap.add_argument("--base", default="paper", help="the variant the others are compared "
                    "with (one of --variants) [default: paper]")
    args, variants = parse_variants(ap, argv, VARIANTS, "paper,half", 3,
                                    "teacher (minutes); tests/test_neural_teacher.py covers "
                                    "the input itself")
    if args.eval_poses < 1:              # before anything is written or measured
        ap.error("--eval-poses: at least 1")
    out = B.start(args, "study_teacher_inputs.py")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    if args.base not in variants:
        ap.error(f"--base {args.base} is not among --variants")
    captures = {v: P._capture(work, log, stage=STAGES.get(v))[0] for v in variants}
    seeds = list(range(args.seeds))
    jobs = [(v, s) for s in seeds for v in variants]
    with ThreadPoolExecutor(max(1, args.workers)) as pool:
        records = list(pool.map(lambda job: _run(work, captures[job[0]], *job, log), jobs))
    every = [_score_all(work, captures[v], v, s) for v, s in jobs]
    import study_env_truth as ET
    poses = args.eval_poses if args.eval_poses != SCALE_EVAL_POSES else None
    texels = P._capture(work, log, stage=ET.stage_of("", "texels", poses))[0]
    with ProcessPoolExecutor(max(1, args.workers), mp_context=get_context("spawn")) as pool:
        consistent = list(pool.map(ET.score_env, *zip(*[
            (str(work), str(texels), v, s, "texels", ET.poses_tag(poses)) for v, s in jobs])))
    rows = list(zip(jobs, records, every, consistent))
    runs = {v: [_seed_row(r, e, c) for (vv, _), r, e, c in rows if vv == v]
            for v in variants}
    record = {"command": B.run_command("study_teacher_inputs.py",
                                       sys.argv[1:] if argv is None else argv),
              "machine": limits, "capture": str(captures[args.base]), "seeds": seeds,
              "base": args.base, "eval_poses": args.eval_poses,
              "stages": {v: STAGES[v] for v in variants if v in STAGES},
              "wall_s": round(time.perf_counter() - t0, 1),
              "variants": {v: VARIANTS[v] for v in variants},
              "by_hand": [f"{v}_s{s}" for (v, s), r in zip(jobs, records) if r.get("note")],
              "results": summarize(runs, seeds, args.base)}
    P.B_write(out / "teacher_inputs.json", record)
    (out / "teacher_inputs.md").write_text(_markdown(record))
    _plot(record, out / "teacher_inputs.png")
    print((out / "teacher_inputs.md").read_text())


def moves(stage: dict) -> bool:
    """Whether a stage's settings move the hand through other poses (its cameras, framed
    on the whole motion, then differ too)."""
    return any(k in stage for k in ("keyframe_every", "frames"))


def _markdown(record: dict) -> str:
    res = record["results"]
    rows_min = sum(v["wall_min"] for v in res.values())
    base = record.get("base", "paper")
    others = [TITLES.get(v, v) for v in record["variants"] if v != base]
    mine = "the paper's" if base == "paper" else f"`{base}` ({TITLES.get(base, base)})"
    title = f"# The OLAT teacher's input: {mine} against " + " and ".join(others or ["itself"])
    lines = [title, "",
             f"Command: `{record['command']}`  ",
             B.machine_line(record["machine"]) + "  ",
             f"Wall time: {record['wall_s'] / 60:.1f} min for this invocation (runs in its "
             f"cache cost nothing); the runs themselves took {rows_min:.1f} min, one core "
             f"each, two at a time; seeds {', '.join(map(str, record['seeds']))}; right "
             f"hand, `converged` capture, `--preset cpu`."
             + (f" Runs by hand (the same command, before this script existed; their cached "
                f"records say so): {', '.join(record['by_hand'])}." if record.get("by_hand")
                else ""), "",
             "| input | held-out PSNR, all samples | gap | SSIM | training poses, all: gap | "
             "held-out PSNR, validation (16) | gap | fully lit gap | env-map gap | env maps, "
             "consistent truth: PSNR | gap | converged | min per run |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def cell(e, split, key):
        s = e.get(split)
        if not s or s.get(key) is None:
            return "—"
        m, sd = s[key]
        return f"{m:.2f} ± {sd:.2f}"
    for v, e in res.items():
        ssim = [r["all_heldout"]["ssim"] for r in e["seeds"]]
        lines.append(f"| {v} ({json.dumps(record['variants'][v])}) | "
                     f"{cell(e, 'all_heldout', 'psnr')} | {cell(e, 'all_heldout', 'gap')} | "
                     f"{sum(ssim) / len(ssim):.4f} | {cell(e, 'all_train', 'gap')} | "
                     f"{cell(e, 'heldout', 'psnr')}"
                     f" | {cell(e, 'heldout', 'gap')} | {cell(e, 'fully_lit', 'gap')} | "
                     f"{cell(e, 'env', 'gap')} | {cell(e, 'env_texels', 'psnr')} | "
                     f"{cell(e, 'env_texels', 'gap')} | {'yes' if e['converged'] else 'NOT'} ("
                     + ", ".join(f"{r['gain_tail_db']:+.2f}" for r in e["seeds"]) + ") | "
                     f"{e['wall_min'] / len(e['seeds']):.1f} |")
    stages = record.get("stages") or {}
    ceil = {s: next((e[s]["ceiling"] for v, e in res.items() if e.get(s) and v not in stages),
                    None) for s in COMPARED}
    lines += ["", "Ceilings (perfect texture through the same compositing and pixel sampling): "
              + ", ".join(f"{s} {c:.2f} dB" for s, c in ceil.items() if c is not None) + ".",
              *[f"{v} is trained and scored on another capture: the `converged` one with "
                f"{json.dumps(st)}, whose held-out, training and fully lit frames are other "
                f"images ({'other poses' if moves(st) else 'other LEDs'}), so it is "
                f"compared on its gap to its own ceilings ("
                + ", ".join(f"{s} {res[v][s]['ceiling']:.2f} dB" for s in COMPARED
                            if res[v].get(s)) + "); the env renders are "
                + ("the same held-out poses through cameras framed on its own motion."
                   if moves(st) else "the same images.")
                for v, st in stages.items()],
              "", f"Against `{base}`, paired by seed (verdict when |difference| > max(2 σ, "
              "0.2 dB)):", ""]
    for v, e in res.items():
        for split, d in (e.get("versus_paper") or {}).items():
            on = (" (gap to its own ceiling)" if d.get("on") == "gap" else
                  " (the same images)" if split in SAME_IMAGES and stages.get(v) else "")
            lines.append(f"- {v}, {split}{on}: {d['diff_db']:+.2f} ± {d['std_db']:.2f} dB → "
                         f"**{d['verdict']}**")
    lines += ["", "Per seed (held-out PSNR / gap in dB, all samples; the validation's 16):", ""]
    for v, e in res.items():
        lines.append(f"- {v}: " + "; ".join(
            f"seed {s}: {r['all_heldout']['psnr']:.2f} / {r['all_heldout']['gap']:.2f} "
            f"({r['heldout']['psnr']:.2f} / {r['heldout']['gap']:.2f})"
            for s, r in zip(record["seeds"], e["seeds"])))
    lines += ["", "Converged: every seed's held-out PSNR gained < 0.2 dB over the last 20 % "
              "of its iterations (on the validation's samples; the column gives each seed's "
              "gain, dB). All samples: every "
              "(frame, camera) image of the held-out poses, scored from the final "
              "checkpoint with its ceiling (`relight_cli.neural.evaluate`), and every "
              "image of the training poses likewise; validation: "
              "the 16 evenly spaced held-out samples, fully lit frames and held-out "
              "env-map renders the training command validates on. Env maps, consistent "
              "truth: every held-out env render of the converged capture made again as its "
              "LEDs are shaded (`eval_env_space: texels`, study_env_truth.py)"
              + (f", with {record['eval_poses']} held-out poses instead of 2"
                 if record.get("eval_poses", SCALE_EVAL_POSES) != SCALE_EVAL_POSES else "")
              + ", the same images for every row. Plot: teacher_inputs.png.", ""]
    return "\n".join(lines)


def plot_seed_curves(ax, record: dict) -> None:
    """One validation curve per seed, one colour per variant (labelled once)."""
    colours = {}
    for v, e in record["results"].items():
        for s, r in zip(record["seeds"], e["seeds"]):
            kw = {"color": colours[v]} if v in colours else {}
            line, = ax.plot([p[0] for p in r["curve"]], [p[1] for p in r["curve"]],
                            marker="o", markersize=3, label=None if s else v, **kw)
            colours.setdefault(v, line.get_color())


def _plot(record: dict, path: Path) -> None:
    import copy
    fig, (ax,) = B.figure()
    if record.get("stages"):
        # variants on other stages validate on other images: plot each one's gap to its
        # own ceiling instead of PSNRs that are not comparable
        record = copy.deepcopy(record)
        for e in record["results"].values():
            for r in e["seeds"]:
                r["curve"] = [[x, r["heldout"]["ceiling"] - y] for x, y in r["curve"]]
    plot_seed_curves(ax, record)
    ceil = next((e["heldout"]["ceiling"] for e in record["results"].values()
                 if e.get("heldout")), None)
    if record.get("stages"):
        ax.axhline(0, color="k", linestyle=":", linewidth=1, label="ceiling")
        ax.set_ylabel("gap to own ceiling (dB), 16 held-out samples")
    elif ceil is not None:
        ax.axhline(ceil, color="k", linestyle=":", linewidth=1, label="ceiling (same samples)")
    ax.set_xlabel("iteration")
    if not record.get("stages"):
        ax.set_ylabel("held-out PSNR, the validation's 16 samples (dB)")
    ax.set_title("OLAT teacher, cpu preset: "
                 + ("the stage" if record.get("stages") else "input channels")
                 + " (one line per seed)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    B.save(fig, path, record["machine"])


if __name__ == "__main__":
    main()
