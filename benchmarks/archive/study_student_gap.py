"""Where the converged student's gap to its ceiling comes from: teacher, env grid, student.

The converged RelightableHands Table 2 (``study_hands.py --scale converged``, table
``rh_t2``) scores each student against the stage's ground-truth env renders (held-out
poses × held-out env maps) beside the ceiling: the perfect texture at the student's N
under the *full* env map, through the same compositing.  A student distilled from a
teacher (Sec. 4.2) can at best reproduce its pseudo ground truth Σ_m b_m C_m — the
teacher's OLAT textures summed over the env map *discretized* to the student's grid
(``env_res``: 8×16 at the ``cpu`` preset, the paper's 16×32).  This scores that target
exactly as the student is scored (same renders, same picks, same metric), for each
seed's teacher row of the study, under both grids, and splits the student's gap:

    ceiling − student = (ceiling − teacher at 16×32)        the teacher's own error
                      + (teacher 16×32 − teacher at 8×16)   the coarser env grid
                      + (teacher 8×16 − student)            distillation (the student's own)

It trains nothing when the study's cache (``--out``) holds the rows: the teacher rows and
the rh_t2 "Ours (student)" rows of each seed are read from it.  Writes ``student_gap.{md,json}``
(no timings inside).  Run (a few minutes on one core)::

    .venv/bin/python benchmarks/study_student_gap.py --out benchmarks/out/study_converged \\
        --results benchmarks/results/converged
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

GRIDS = ((8, 16), (16, 32))


def teacher_vs_ground_truth(study, row: dict, samples: int) -> dict:
    """{grid: metrics, "ceiling": metrics} of the teacher ``row``'s env renders (its
    per-direction textures under the env map discretized to each grid) against the
    capture's held-out env renders, picked as :func:`relight_cli.neural.distill.
    evaluate_student` picks them."""
    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.neural import distill as D
    from relight_cli.neural.ceiling import ceiling_of
    from relight_cli.neural.checkpoints import teacher_model

    teacher, tconfig, mean = teacher_model(read_checkpoint(row["checkpoint"], kind="teacher"))
    data = study.data(study.capture("right"), tconfig)
    renders = data.splits()["env"]
    pick = np.unique(np.linspace(0, len(renders) - 1, min(len(renders), samples))
                     .round().astype(int))
    ceiling = ceiling_of(data)
    out = {}
    for grid in GRIDS:
        rows, best, targets = [], [], None
        for i in pick:
            pose, env_name, camera, gt, mask = data.env_target(renders[i][1])
            denv = discretize_env(data.env_map(env_name), *grid)
            if targets is None:
                targets = D.TeacherTargets(teacher, tconfig, data, denv, None, 8192, "cpu",
                                           mean, identity=row["key"])
            pred = targets.image(pose, camera.name, denv, held_out=True).numpy()
            rows.append(D._metrics(pred, gt, mask))
            texels = data.texels(pose, held_out=True)
            best.append(ceiling.score(renders[i], [texels] * texels.n_hands,
                                      data.gbuffer(pose, camera, held_out=True), gt, mask))
        out[f"{grid[0]}x{grid[1]}"] = {k: float(np.mean([r[k] for r in rows]))
                                       for k in ("mse", "psnr", "ssim")}
        out["ceiling"] = {k: float(np.mean([r[k] for r in best])) for k in ("mse", "psnr", "ssim")}
        out["samples"] = len(rows)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the converged study's cache (--out of "
                                                 "study_hands.py): its teacher rows")
    ap.add_argument("--results", required=True, help="gets student_gap.{md,json}")
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args(argv)
    import torch
    torch.set_num_threads(1)
    import study_hands as S

    results = Path(args.results)
    study = S.Study("converged", Path(args.out), log=lambda m: print(m, file=sys.stderr))
    samples = int(study.settings["val_samples"])
    t2 = S.TABLES["rh_t2"]
    seeds = []
    for seed in range(args.seeds):
        # the study's cached rows (trained by study_hands.py; this trains nothing new
        # when its cache holds them)
        row = study.row("teacher", "right", {}, seed, ("heldout",), ("heldout", "mse"))
        trained = study.row("student", "right", t2.rows["Ours (student)"], seed, t2.splits,
                            t2.curve, row)
        ref = teacher_vs_ground_truth(study, row, samples)
        psnr = trained["metrics"]["vs_ground_truth"]["psnr"]
        ceiling = ref["ceiling"]["psnr"]
        seeds.append({"seed": seed, "teacher_key": row["key"], "teacher": ref,
                      "student_psnr": psnr,
                      "split_db": {"teacher": ceiling - ref["16x32"]["psnr"],
                                   "env_grid": ref["16x32"]["psnr"] - ref["8x16"]["psnr"],
                                   "distillation": ref["8x16"]["psnr"] - psnr,
                                   "total": ceiling - psnr}})
    record = {"command": S.portable("python benchmarks/study_student_gap.py " + " ".join(
        sys.argv[1:] if argv is None else argv)), "machine": S.machine(), "seeds": seeds}
    from relight_cli.provenance import write_text_atomic
    write_text_atomic(str(results / "student_gap.json"), json.dumps(record, indent=1) + "\n")
    write_text_atomic(str(results / "student_gap.md"), markdown(record))
    print(markdown(record))
    return 0


def markdown(record: dict) -> str:
    def mean(f):
        return float(np.mean([f(s) for s in record["seeds"]]))
    lines = ["# Where the converged student's gap to its ceiling comes from", "",
             f"Command: `{record['command']}`  ", f"Machine: {record['machine']}", "",
             "Held-out poses × held-out env maps of the converged right-hand capture, "
             "against the stage's ground-truth env renders (PSNR, dB, mean over the "
             "study's picks), per seed of `study_rh_t2`:", "",
             "| seed | ceiling | teacher, env at 16×32 | teacher, env at 8×16 (the "
             "student's target) | student | teacher's error | 8×16 grid | distillation | "
             "total gap |", "|---|---|---|---|---|---|---|---|---|"]
    for s in record["seeds"]:
        t, d = s["teacher"], s["split_db"]
        lines.append(f"| {s['seed']} | {t['ceiling']['psnr']:.2f} | {t['16x32']['psnr']:.2f} | "
                     f"{t['8x16']['psnr']:.2f} | {s['student_psnr']:.2f} | {d['teacher']:.2f} "
                     f"| {d['env_grid']:.2f} | {d['distillation']:.2f} | {d['total']:.2f} |")
    part = {k: mean(lambda s: s["split_db"][k])
            for k in ("teacher", "env_grid", "distillation", "total")}
    lines += ["", f"Mean over seeds: the teacher's own error {part['teacher']:.2f} dB, "
              f"the 8×16 env grid {part['env_grid']:.2f} dB, "
              f"distillation {part['distillation']:.2f} dB, total {part['total']:.2f} dB.", "",
              "The teacher columns are the pseudo ground truth Σ_m b_m C_m "
              "(`relight_cli.neural.distill.TeacherTargets`) under the env map discretized "
              "to that grid; the ceiling is the perfect texture at the student's N under the "
              "full env map (`relight_cli.neural.ceiling`). The student column is the "
              "table's own row (`study_rh_t2.json`, `Ours (student)`).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
