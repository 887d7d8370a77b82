"""URHand's quick personalisation (Sec. 5.4, supp. 9), scored against the stage's truth.

For each unseen subject of the identity study (``study_hands.py --tables ur_id``: shapes
and skins no trained subject has) and each seed of its universal linear model:

1. the stage renders a phone scan of the subject (``synth-capture --phone-scan``: its
   shape and skin, a still hand in a neutral pose, ``--views`` photos under one smooth
   env map, ``builtin:sky``, which is not among the capture's held-out maps);
2. ``relight personalize`` fits the hand to the photos and unwraps its mean texture T̄,
   dividing the scan's lighting out either with the map known (``env``) or estimated
   (``statistical``, supp. 9's shading map, its level from the checkpoint);
3. ``relight CAPTURE/ --subject`` scores the universal model given that T̄ on the
   capture's held-out poses under its held-out env maps (Poly Haven's studio_small_03 and
   venice_sunset), beside (a) the same model given the subject's true T̄ (the capture's
   own, the ``unseen`` row of the identity table) and (b) the ceiling (the perfect
   texture through the same compositing and pixel sampling);
4. the fitted bone lengths against the subject's true ones (and the template's).

Every step runs the commands a user runs (subprocesses) and is timed.  Results:
``RESULTS.md`` / ``RESULTS.json``; previews of each personalised hand under the two
held-out maps in ``--work``; ``--out`` gets personalize.{md,json,png} (the plot: each
row's loss against the true T̄ over the seconds personalisation took).  ``--quick``: one
unseen subject, the first seed, 4 photos of 128², 40 iterations.

    .venv/bin/python benchmarks/bench_personalize.py --study benchmarks/out/study_converged \\
        --out benchmarks/results/converged
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RELIGHT = [str(Path(sys.executable).with_name("relight"))]


def run(args, log) -> float:
    """Run ``relight ARGS`` (quiet), raise on failure; its wall time in seconds."""
    start = time.perf_counter()
    r = subprocess.run([*RELIGHT, *map(str, args), "-q"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"relight {' '.join(map(str, args))} failed:\n{r.stderr}")
    seconds = time.perf_counter() - start
    log(f"  {seconds:6.1f} s  relight {' '.join(map(str, args))[:150]}")
    return seconds


def unseen_subjects(study: Path) -> list:
    """(name, capture folder) of the identity study's unseen subjects."""
    record = json.loads((ROOT / "benchmarks/results/converged/study_ur_id.json").read_text())
    out = []
    for folder in sorted((study / "captures").iterdir()):
        if folder.is_dir() and (folder / "capture.json").exists():
            name = folder.name.rsplit("-", 1)[0]
            if name in record.get("unseen_subjects", UNSEEN):
                out.append((name, folder))
    return out


UNSEEN = ("wave-3", "webxrL-4", "template-5")


def universal_checkpoints(study: Path) -> list:
    """The identity study's trained universal models (``runs/KEY.json`` naming a
    ``checkpoint``; one per seed), in seed order."""
    found = []
    for meta in sorted((study / "runs").glob("*.json")):
        if ".partial" in meta.name:
            continue
        info = json.loads(meta.read_text())
        path = info.get("checkpoint")
        if path and Path(path).is_file() and info.get("kind", "identity") in ("identity",
                                                                              "linear"):
            found.append((info.get("seed", len(found)), Path(path)))
    return [p for _, p in sorted(found)]


def bone_lengths(rest, parents) -> np.ndarray:
    return np.array([np.linalg.norm(rest[j] - rest[parents[j]]) for j in range(1, len(rest))])


def metrics(path: Path, split: str = "env") -> dict:
    m = json.loads(path.read_text())["metrics"][split]
    return {k: m.get(k) for k in ("psnr", "ssim", "gap_to_ceiling", "samples")}


def main(argv=None):
    ap = B.parser(__doc__, "one unseen subject, the first seed, 4 photos of 128², 40 "
                           "iterations")
    ap.add_argument("--study", type=Path, default=ROOT / "benchmarks/out/study_converged")
    ap.add_argument("--checkpoints", type=Path, nargs="*", default=None,
                    help="universal linear checkpoints [default: the study's, one per seed]")
    ap.add_argument("--scan-env", default="builtin:sky")
    ap.add_argument("--views", type=B.integer(2), default=8)
    ap.add_argument("--size", type=B.integer(32), default=256)
    ap.add_argument("--iterations", type=B.integer(1), default=200)
    ap.add_argument("--work", type=Path, default=B.OUT / "personalize_work", metavar="DIR",
                    help="scans, subjects, scores and previews (a cache: scans are reused)")
    a = ap.parse_args(argv)
    if a.quick:
        a.views, a.size, a.iterations = 4, 128, 40
    results = B.start(a, "bench_personalize.py", {"--work": a.work}) / "personalize"
    a.out = a.work
    a.out.mkdir(parents=True, exist_ok=True)
    machine = B.machine_limits()
    log_lines = []

    def log(message):
        print(message, flush=True)
        log_lines.append(message)

    from relight_cli.formats.hand_npz import read_hand
    from relight_cli.hand.model import PARENTS, builtin_hand
    checkpoints = a.checkpoints or universal_checkpoints(a.study)
    if a.quick:
        checkpoints = checkpoints[:1]
    if not checkpoints:
        raise SystemExit(f"no trained universal model under {a.study}/runs (run the study)")
    template = bone_lengths(builtin_hand().rest_joints, PARENTS)
    rows = []
    for name, capture in unseen_subjects(a.study)[:1 if a.quick else None]:
        info = json.loads((capture / "capture.json").read_text())
        settings = info["settings"]
        hand = capture / info["hand"]
        truth = bone_lengths(read_hand(str(hand)).rest_joints, PARENTS)
        scan = a.out / f"scan_{name}"
        log(f"{name}: skin {settings['skin_seed']}, scan of {a.views} photos under {a.scan_env}")
        timing = a.out / f"scan_{name}.seconds"          # the render's time, kept with the cache
        if not (scan / "keypoints.json").exists():
            timing.write_text("%.1f\n" % run([
                          "synth-capture", hand, "--phone-scan", a.scan_env, "--views", a.views,
                          "--size", a.size, "--tex-res", settings["tex_res"], "--aa",
                          settings["aa"], *([] if settings["sss"] else ["--no-sss"]),
                          "--skin-seed", settings["skin_seed"], "-o", scan], log))
        t_scan = float(timing.read_text()) if timing.exists() else None
        photos = sorted(scan.glob("view_*.exr"))
        envs = sorted((capture / "eval" / "envs").glob("*.exr"))
        for seed, ckpt in enumerate(checkpoints):
            row = {"subject": name, "seed": seed, "skin_seed": settings["skin_seed"],
                   "views": a.views, "scan_seconds": t_scan}
            common = ["relight", capture, "--model", "linear", "--checkpoint", ckpt,
                      "--splits", "env"]
            oracle = a.out / f"{name}_s{seed}_oracle.json"
            row["oracle_seconds"] = round(run([*common, "-o", oracle], log), 1)
            row["oracle"] = metrics(oracle)
            for lighting in ("env", "statistical"):
                me = a.out / f"{name}_s{seed}_{lighting}.npz"
                extra = ["--env", a.scan_env] if lighting == "env" else []
                seconds = run(["personalize", *photos, "--cameras", scan / "cameras.json",
                               "--keypoints", scan / "keypoints.json", "--checkpoint", ckpt,
                               "--iterations", a.iterations, *extra, "-o", me, "--report",
                               me.with_suffix(".json")], log)
                scores = a.out / f"{name}_s{seed}_{lighting}_scores.json"
                run([*common, "--subject", me, "-o", scores], log)
                fitted = read_hand(str(me))
                report = json.loads(me.with_suffix(".json").read_text())
                row[lighting] = {**metrics(scores), "personalize_seconds": round(seconds, 1),
                                 "reprojection_px": round(float(np.mean(
                                     [v["reprojection_px"] for v in report["views"]])), 3),
                                 "seen_fraction": report["texels"]["seen_fraction"]}
                if lighting == "env":
                    err = np.abs(bone_lengths(fitted.rest_joints, PARENTS) - truth) * 1000
                    row["bone_mm"] = {"fitted_mean": round(float(err.mean()), 3),
                                      "fitted_max": round(float(err.max()), 3),
                                      "template_mean": round(float(np.abs(template - truth).mean()
                                                                   * 1000), 3)}
                    if seed == 0:
                        for env in envs:
                            png = a.out / f"{name}_{env.stem}.png"
                            run(["relight", me, env, "--model", "linear", "--checkpoint", ckpt,
                                 "--size", "256x256", "-o", a.out / f"{name}_{env.stem}.exr",
                                 "--preview", png], log)
            rows.append(row)
            log(f"  {name} seed {seed}: oracle {row['oracle']['psnr']:.2f} dB, env "
                f"{row['env']['psnr']:.2f}, statistical {row['statistical']['psnr']:.2f} "
                f"(ceiling gap of the oracle {row['oracle']['gap_to_ceiling']:.2f} dB)")
    record = {"command": B.run_command("bench_personalize.py",
                                       sys.argv[1:] if argv is None else argv),
              "quick": a.quick, "machine": B.machine_line(machine), "limits": machine,
              "scan_env": a.scan_env, "views": a.views, "size": a.size,
              "checkpoints": [str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p)
                              for p in checkpoints],
              "rows": rows}
    results.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    results.with_suffix(".md").write_text(markdown(record))
    plot(record, results.with_suffix(".png"), machine)
    print(markdown(record))


def markdown(record: dict) -> str:
    rows = record["rows"]
    lines = ["# Quick personalisation from a phone scan (URHand Sec. 5.4, supp. 9)", "",
             f"Command: `{record['command']}`  ",
             f"{record['machine']}  ",
             f"Scan: {record['views']} photos of {record['size']}² under {record['scan_env']}; "
             "scored on each unseen subject's held-out poses under its capture's held-out env "
             "maps (split `env`), linear radiance inside the hand mask.", "",
             "| subject | seed | true T̄ (oracle) PSNR | personalised, env known | "
             "personalised, estimated | ceiling | oracle gap | env − oracle | "
             "estimated − oracle | bone mm (fit / template) | reproj. px |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        o, e, s = r["oracle"], r["env"], r["statistical"]
        ceiling = o["psnr"] + o["gap_to_ceiling"] if o["gap_to_ceiling"] is not None else None
        lines.append(
            f"| {r['subject']} | {r['seed']} | {o['psnr']:.2f} | {e['psnr']:.2f} | "
            f"{s['psnr']:.2f} | {ceiling:.2f} | {o['gap_to_ceiling']:.2f} | "
            f"{e['psnr'] - o['psnr']:+.2f} | {s['psnr'] - o['psnr']:+.2f} | "
            f"{r['bone_mm']['fitted_mean']:.2f} / {r['bone_mm']['template_mean']:.2f} | "
            f"{e['reprojection_px']:.2f} |")
    if rows:
        de = np.array([r["env"]["psnr"] - r["oracle"]["psnr"] for r in rows])
        ds = np.array([r["statistical"]["psnr"] - r["oracle"]["psnr"] for r in rows])
        lines += ["", f"Personalised (env known) − true T̄: {de.mean():+.2f} ± {de.std():.2f} "
                      f"dB; "
                      f"estimated lighting − true T̄: {ds.mean():+.2f} ± {ds.std():.2f} dB "
                      f"(mean ± std over {len(rows)} subject × seed rows).",
                  "", "Seconds per step (2 cores): scan render "
                  + ", ".join(f"{r['subject']} {r['scan_seconds']}" for r in rows if r['seed'] == 0)
                  + "; personalize (env) "
                  + ", ".join(f"{r['env']['personalize_seconds']}" for r in rows)
                  + "; scoring the oracle " + ", ".join(f"{r['oracle_seconds']}" for r in rows)
                  + "."]
    return "\n".join(lines) + "\n"


def plot(record: dict, path: Path, machine: dict) -> None:
    """Each row's loss against the true T̄ (dB) over the seconds its personalisation took,
    one curve per way of dividing the lighting out."""
    fig, (ax,) = B.figure(1)
    curves = {}
    for lighting, name in (("env", "env map known"), ("statistical", "estimated (supp. 9)")):
        curves[name] = sorted((r[lighting]["personalize_seconds"],
                               max(r["oracle"]["psnr"] - r[lighting]["psnr"], 1e-3),
                               f"{r['subject']}/{r['seed']}") for r in record["rows"])
    B.plot(ax, curves, "personalize wall time (s)", "PSNR loss against the true T̄ (dB)",
           "quick personalisation: time against error", logy=False)
    B.save(fig, path, machine)


if __name__ == "__main__":
    B.run_main("bench_personalize.py", main)
