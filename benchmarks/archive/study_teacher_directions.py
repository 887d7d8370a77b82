"""Where the OLAT teacher's env-map error lives: its texture under each bright direction
of an env map against the stage's own texture under that direction alone.

The ``cpu`` student's largest share of its gap to the ceiling is its teacher's error
under env maps (results/converged/student_grid/: 1.85 dB of 2.95), which neither a finer
env grid (16×32 → 32×64: +0.02 to +0.08 dB per seed) nor four times as many LEDs
(results/converged/teacher_lights/, a tie under env maps) removes.  An env render is,
by the linearity of light transport (RelightableHands Eq. 2), a sum over directions of
b_m C_m; so, on every held-out env render of the capture with consistent env truth
(``eval_env_space: texels``), for the ``--directions`` brightest directions of its
16×32 grid (b_m = L_m Δω_m), this compares the teacher's b_m C_m with the stage's own
texture when direction m is the only light (:class:`relight_cli.render.capture.
StageShader` on a one-direction env map, the texel centres of the teacher's N), over the
texels inside the charts that face the render's camera:

* ``rel``: the energy-weighted relative squared error Σ|b_m C_m − P_m|² / Σ|P_m|²;
* where it lies: texels facing the light (l_z > 0.3, visible), grazing (0 < l_z ≤ 0.3,
  visible), shadowed (l_z > 0, occluded), facing away (l_z ≤ 0);
* ``corr``: the correlation, over those directions, of a direction's relative error with
  its angle to the nearest LED (seen from the hand's centre): near 0 when the error does
  not come from the directions between the LEDs;
* ``summed``: the relative squared error of the summed textures Σ_m b_m C_m against
  Σ_m P_m, and their relative bias: if the per-direction errors were independent, the
  sum's relative error would fall as the directions add up.

Trains nothing (the teachers of study_teacher_inputs.py, ``--work``); per render cached as
``--cache``/[TEACHER_]directionsK_sS_rR.json (K directions).  Writes
``teacher_directions.{md,json}`` to ``--out``.  ``--teacher`` names another
study_teacher_inputs.py variant trained on the same LED frames (default ``paper``).  Run
(the teachers cached: about 75 s on 2 cores)::

    .venv/bin/python benchmarks/study_teacher_directions.py --seeds 3 --workers 2 \\
        --directions 64 --work benchmarks/out/teacher_inputs \\
        --out benchmarks/results/converged/teacher_directions
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
import bench_presets as P  # noqa: E402

#: the env grid of the teacher's pseudo ground truth (the paper's)
GRID = (16, 32)
#: the shares of the error, by where the texel stands to the light
PLACES = ("lit", "grazing", "shadowed", "away")


def _render_rows(work: str, capture: str, seed: int, index: int, directions: int,
                 cache: str, teacher: str = "paper", tag: str = "") -> dict:
    """One held-out env render of seed ``seed``'s ``teacher`` (a study_teacher_inputs.py
    variant; cached in ``cache``, per number of directions)."""
    name = "" if teacher == "paper" else f"{teacher}_"
    path = Path(cache) / f"{name}directions{directions}_s{seed}_r{index}{tag}.json"
    if path.is_file():
        return json.loads(path.read_text())
    import numpy as np
    import torch

    import study_student_env as E
    from relight_cli.envmap import discretize_env
    from relight_cli.neural.ceiling import ceiling_of
    torch.set_num_threads(1)
    data, targets = E._targets(str(Path(work) / f"{teacher}_s{seed}.pt"), capture, None, GRID)
    pose, env_name, camera, _, _ = data.env_target(data.splits()["env"][index][1])
    denv = discretize_env(data.env_map(env_name), *GRID)
    textures = np.asarray(targets.textures(pose, camera.name, True))
    texels = data.texels(pose, held_out=True)
    ceiling = ceiling_of(data)
    renderer = ceiling.shader.renderer(data.meshes(pose, True))
    lights = texels.directional_lights(0, denv.directions, visibility=True)
    facing = texels.inside(0) & (texels.to_maps(0, texels.local_view(0, camera.center)
                                                [:, 2:3])[0] > 0)
    b = denv.radiance * denv.solid_angle[:, None]
    energy = b.mean(1)
    picked = np.argsort(-energy)[:directions]
    centre = np.concatenate([s.points for s in texels.surfaces]).mean(0)
    leds = np.asarray(data.capture.light_positions, np.float64) - centre
    leds /= np.linalg.norm(leds, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(denv.directions @ leds.T, -1, 1))).min(1)

    def to_map(values):
        return texels.to_maps(0, np.asarray(values, np.float32)[:, None])[0]
    err, ref, places, per_dir = 0.0, 0.0, dict.fromkeys(PLACES, 0.0), []
    sum_teacher = np.zeros(textures.shape[2:], np.float64)
    sum_stage = np.zeros_like(sum_teacher)
    for m in picked:
        radiance = np.zeros_like(denv.radiance)
        radiance[m] = denv.radiance[m]
        lit = renderer.light(env=replace(denv, radiance=radiance))
        stage = texels.to_maps(0, ceiling.shader.texel_radiance(
            renderer, lit, [texels.surfaces[0]], camera.center)[0].astype(np.float32))
        ours = textures[0, m] * b[m][:, None, None]
        sum_teacher += ours
        sum_stage += stage
        sq = ((ours - stage) ** 2).mean(0)
        lz, vis = to_map(lights.local_light[m, :, 2]), to_map(lights.visibility[m])
        masks = {"lit": (lz > 0.3) & (vis > 0.5), "grazing": (lz > 0) & (lz <= 0.3) & (vis > 0.5),
                 "shadowed": (lz > 0) & (vis <= 0.5), "away": lz <= 0}
        for name, mask in masks.items():
            places[name] += float(sq[facing & mask].sum())
        e, r = float(sq[facing].sum()), float((stage ** 2).mean(0)[facing].sum())
        err, ref = err + e, ref + r
        per_dir.append((e / max(r, 1e-30), float(angle[m])))
    rel = np.array(per_dir)
    diff = (sum_teacher - sum_stage).mean(0)[facing]
    row = {"teacher": teacher, "seed": seed, "render": index, "env": env_name, "pose": int(pose),
           "camera": camera.name, "directions": int(len(picked)),
           "energy_share": float(energy[picked].sum() / energy.sum()),
           "rel": err / ref, "places": {k: v / err for k, v in places.items()},
           "corr": float(np.corrcoef(rel[:, 0], rel[:, 1])[0, 1]),
           "summed": float(((sum_teacher - sum_stage) ** 2).mean(0)[facing].sum()
                           / (sum_stage ** 2).mean(0)[facing].sum()),
           "bias": float(diff.sum() / sum_stage.mean(0)[facing].sum())}
    P.B_write(path, row)
    return row


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "teacher_inputs"), metavar="DIR",
                    help="study_teacher_inputs.py's cache: captures and teachers")
    ap.add_argument("--cache", default=str(B.OUT / "teacher_directions"), metavar="DIR",
                    help="where each render's numbers are kept")
    ap.add_argument("--teacher", default="paper",
                    help="the study_teacher_inputs.py variant (one trained on another stage "
                    "is scored on the same renders) [default: paper]")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--directions", type=int, default=24,
                    help="brightest directions per render [default: 24]")
    ap.add_argument("--eval-poses", type=int, default=2, metavar="N",
                    help="held-out poses of the env renders (a capture of its own; the "
                    "held-out poses are other images than the converged capture's) [default: 2]")
    args = ap.parse_args(argv)
    if args.quick:
        ap.error("no --quick: the teachers are converged cpu-preset runs")
    if args.eval_poses < 1:
        ap.error("--eval-poses: at least 1")
    import study_env_truth as ET
    import study_teacher_inputs as T
    if args.teacher not in T.VARIANTS:
        ap.error(f"--teacher: one of {', '.join(T.VARIANTS)}")
    out = B.start(args, "study_teacher_directions.py")
    work = Path(args.work)
    t0 = time.perf_counter()
    limits = B.machine_limits()

    def log(m):
        print(m, file=sys.stderr, flush=True)
    # every teacher, one of another stage (study_teacher_inputs.STAGES) too, on the
    # converged capture's env renders: the same images, poses and cameras for all
    poses = args.eval_poses if args.eval_poses != T.SCALE_EVAL_POSES else None
    capture = P._capture(work, log, stage=ET.stage_of("", "texels", poses))[0]
    for seed in range(args.seeds):               # the teachers train on the LED frames
        T._run(work, P._capture(work, log, stage=T.STAGES.get(args.teacher))[0],
               args.teacher, seed, log)
    from relight_cli.neural.config import resolve_config
    from relight_cli.neural.data import CaptureData
    renders = len(CaptureData(str(capture), resolve_config("cpu").tex_res).splits()["env"])
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    jobs = [(str(work), str(capture), s, r, args.directions, args.cache, args.teacher,
             ET.poses_tag(poses)) for s in range(args.seeds) for r in range(renders)]
    with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(_render_rows, *zip(*jobs)))
    record = {"command": B.run_command("study_teacher_directions.py", argv or sys.argv[1:]),
              "teacher": args.teacher,
              "machine": limits, "wall_s": time.perf_counter() - t0, "grid": list(GRID),
              "capture": capture.name, "rows": rows}
    P.B_write(out / "teacher_directions.json", record)
    text = _markdown(record)
    (out / "teacher_directions.md").write_text(text)
    print(text)


def _markdown(record: dict) -> str:
    import numpy as np
    rows = record["rows"]
    head = (f"Command: `{record['command']}`  \n{B.machine_line(record['machine'])}  \n"
            f"Wall time: {record['wall_s'] / 60:.1f} min for this invocation (renders in its "
            f"cache cost nothing); the `{record.get('teacher', 'paper')}`-input `cpu` teacher of ")
    lines = ["# Where the OLAT teacher's env-map error lives", "",
             head +
             f"each seed, every held-out env render of `{record['capture']}` (consistent env "
             f"truth), the brightest directions of its {record['grid'][0]}×{record['grid'][1]} "
             "grid, the texels inside the charts that face the render's camera.", "",
             "| seed | render | env | pose | camera | directions (energy share) | per-direction "
             "rel. sq. error | lit | grazing | shadowed | facing away | corr. with angle to "
             "nearest LED | summed: rel. sq. error | summed: bias |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["places"]
        lines.append(f"| {r['seed']} | {r['render']} | {r['env']} | {r['pose']} | "
                     f"{r['camera']} | {r['directions']} "
                     f"({100 * r['energy_share']:.0f} %) | {r['rel']:.4f} | "
                     + " | ".join(f"{100 * p[k]:.0f} %" for k in PLACES)
                     + f" | {r['corr']:+.2f} | {r['summed']:.4f} | {100 * r['bias']:+.1f} % |")

    def mean(values):
        return f"{np.mean(values):.4f} (range {min(values):.4f}–{max(values):.4f})"
    lines += ["", f"Over the {len(rows)} renders: per-direction relative squared error "
              f"{mean([r['rel'] for r in rows])}; summed textures "
              f"{mean([r['summed'] for r in rows])}; on lit texels "
              f"{100 * np.mean([r['places']['lit'] for r in rows]):.0f} % of the error, "
              f"shadowed {100 * np.mean([r['places']['shadowed'] for r in rows]):.0f} %; "
              f"correlation with the angle to the nearest LED "
              f"{np.mean([r['corr'] for r in rows]):+.2f} (range "
              f"{min(r['corr'] for r in rows):+.2f} to {max(r['corr'] for r in rows):+.2f}).",
              "", "Per camera (all seeds, renders and env maps): " + "; ".join(
                  f"{cam}: per-direction {mean([r['rel'] for r in rows if r['camera'] == cam])}"
                  f", bias {100 * min(r['bias'] for r in rows if r['camera'] == cam):+.1f} % to "
                  f"{100 * max(r['bias'] for r in rows if r['camera'] == cam):+.1f} %"
                  for cam in sorted({r["camera"] for r in rows})) + ".",
              "", "Per-direction: Σ_m |b_m C_m − P_m|² / Σ_m |P_m|² over the picked directions "
              "(P_m the stage's texture with direction m alone); summed: the same of Σ_m b_m C_m "
              "against Σ_m P_m; bias: Σ (teacher − stage) / Σ stage over the facing texels."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
