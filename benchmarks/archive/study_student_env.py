"""What limits the converged student: per-texel biases and the number of env maps it
learns from, at the ``cpu`` preset, to convergence, over seeds.

The converged Table 2 (``results/converged/study_rh_t2.md``) left the student 10 dB below
its ceiling, 4.9 dB of it in distillation itself (``results/converged/student_gap.md``).
Scored against its own teacher, that student's error on held-out poses is 2.5× larger
under the two held-out env maps than under the seven it trained on (and 1.9× larger on
held-out poses than on trained ones): it learns the few env maps a capture comes with
rather than lighting.  The paper distills on 2,560 env maps; the study has 7 (three
built-ins and four Poly Haven HDRIs).  Two changes are measured, alone and together:

- ``untied_bias`` (the authors' code builds its decoders with per-texel biases; the paper's
  text does not say): the student's only spatially varying inputs are lighting
  features, so without them it cannot hold a per-texel albedo;
- ``env_augment: mix`` (ours): every training sample's env map is synthesized from the
  training maps — a mixture of up to three, each rotated, mirrored and tinted, plus a
  random sun cell (:func:`relight_cli.neural.distill.mix_env`).  Every step is a
  non-negative linear map of the grid's radiances, so the teacher's pseudo ground truth
  stays exact and costs no teacher pass.

DRAM (Table 2's baseline, ``student: dram``) is run on the training maps alone and with
synthesized ones: its only lighting input is the env map seen from the wrist, so it is
the model that most needs more than seven maps (its converged curve is flat from the
first validation).

``linear``, ``linear_lsq`` and ``lsq`` (``head: linear``, ours) replace Eq. 11's head
by per-texel weights of the student's own features, decoded from the pose alone, so the
texture is linear in the env map (:class:`relight_cli.neural.student.LinearHeadStudent`):
``linear`` starts from a grey texture, ``linear_lsq`` from the per-texel least-squares fit
of the teacher's textures (``head_init: lsq``), and ``lsq`` is that closed-form fit alone
(``iters`` 0, about a minute).  Why: a per-texel least-squares fit of the features, by
hand on seed 0 (40 samples per split), scored above the converged paper-text student
against the teacher: 25.00 against 22.14 dB on held-out poses × held-out maps, 26.71
against 25.05 on trained poses × training maps (the student does not fit its own
training data).  Result: results/converged/student_linear/.

``linear_tex`` is the ``cpu`` preset's student distilled on whole textures
(``loss_space: texture``, which trains DRAM's light path) against ``linear``: 5 dB worse
(results/converged/student_linear_tex/), the texels its camera does not see pulling on
those it does.  ``linear_mix`` is it on synthesized env maps (``env_augment: mix``): a
tie (results/converged/student_linear_mix/), a texture linear in the env map carrying to
new maps by construction.

``tied_8k`` is the paper's text trained twice as long (8,000 iterations, the cosine decay
stretched to match): whether the ``cpu`` preset's 4,000 stop a student that is still
learning (half of the 4,000-iteration runs still gain > 0.2 dB in their last 1,000).

Each student is the command a user runs, ``relight distill TEACHER CAPTURE --envs …
--eval-envs … --preset cpu --config VARIANT.json --seed S --cache DIR`` (one thread each,
``--workers`` at a time), distilled from the ``paper``-input ``cpu`` OLAT teacher of the
same seed (``study_teacher_inputs.py``'s runs, trained here when absent, in
``--teachers``), on the study's ``converged`` right-hand capture.  The variants share each
teacher's per-direction textures through the disk cache (``cache_mb`` 0: computed once
per (pose, camera), in ``--workers`` processes before the students start).  After
training, each checkpoint is scored against its teacher on every held-out (frame, camera)
× each held-out env map, and on 128 evenly spaced held-out-pose × training-map and
trained-pose × held-out-map samples; against the ground truth on every held-out env
render of the capture, with its ceiling (``--metrics-out``).  A variant's difference from
``tied`` (the paper's text; ``dram_mix``'s from ``dram``) is a verdict only when it exceeds
max(2 σ over seeds, 0.2 dB) (the study_hands rule).  Writes ``student_env.{md,json,png}``
to ``--out``.  Run (about 17 min per student on one core of a 2-core AMD EPYC, two at a
time, and ~10 min per seed for the teacher's textures: 2 seeds × 6 variants ≈ 2 h with
the teachers cached; ``--variants tied,untied_mix`` ≈ 1 h)::

    .venv/bin/python benchmarks/study_student_env.py --seeds 2 --workers 2 \\
        --work benchmarks/out/student_env --teachers benchmarks/out/teacher_inputs \\
        --out benchmarks/results/converged
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as B  # noqa: E402
import bench_presets as P  # noqa: E402
import study_teacher_inputs as T  # noqa: E402

#: every texel-aligned variant names its head: the ``cpu`` preset's is ``linear`` (since
#: this study), the paper's Eq. 11 head is ``eq11``
VARIANTS = {"tied": {"untied_bias": False, "env_augment": "paper", "head": "eq11"},
            "untied": {"untied_bias": True, "env_augment": "paper", "head": "eq11"},
            "mix": {"untied_bias": False, "env_augment": "mix", "head": "eq11"},
            "untied_mix": {"untied_bias": True, "env_augment": "mix", "head": "eq11"},
            "dram": {"student": "dram", "env_augment": "paper"},
            "dram_mix": {"student": "dram", "env_augment": "mix"},
            # DRAM with Eq. 11's head scale (the student's lambda_s 25), its head before
            # the presets put it in texture units (relight_cli.neural.config.DRAM_LAMBDA_S)
            "dram_eq11": {"student": "dram", "env_augment": "paper", "lambda_s": 25.0},
            # DRAM on the same 8,000 samples in batches of 8 (1,000 steps; validation,
            # the negative-light penalty's start and saves scaled with them)
            "dram_b8": {"student": "dram", "env_augment": "paper", "batch": 8, "iters": 1000,
                        "neg_start": 250, "val_every": 250, "save_every": 250},
            # DRAM distilled on its whole texture (``loss_space: texture``, ours) instead
            # of the camera's image (the paper's)
            "dram_tex": {"student": "dram", "env_augment": "paper", "loss_space": "texture"},
            "dram_tex_b8": {"student": "dram", "env_augment": "paper", "loss_space": "texture",
                            "batch": 8, "iters": 1000, "neg_start": 250, "val_every": 250,
                            "save_every": 250},
            # ... and on env maps synthesized from the training maps (``env_augment: mix``)
            "dram_tex_b8_mix": {"student": "dram", "env_augment": "mix",
                                "loss_space": "texture", "batch": 8, "iters": 1000,
                                "neg_start": 250, "val_every": 250, "save_every": 250},
            "tied_8k": {"untied_bias": False, "env_augment": "paper", "iters": 8000,
                        "head": "eq11"},
            "linear": {"head": "linear", "env_augment": "paper"},
            "linear_lsq": {"head": "linear", "head_init": "lsq", "env_augment": "paper"},
            "lsq": {"head": "linear", "head_init": "lsq", "env_augment": "paper", "iters": 0},
            "linear_8k": {"head": "linear", "env_augment": "paper", "iters": 8000},
            # the cpu preset's student distilled on its whole texture (``loss_space:
            # texture``, ours) instead of the camera's image (the paper's)
            "linear_tex": {"head": "linear", "env_augment": "paper", "loss_space": "texture"},
            # ... and on env maps synthesized from the training maps (``env_augment: mix``)
            "linear_mix": {"head": "linear", "env_augment": "mix"},
            # the cpu preset's student distilled from the OLAT teacher with the shading
            # features as input (study_teacher_inputs.py's ``shading`` variant)
            "linear_tshading": {"head": "linear", "env_augment": "paper",
                                "teacher": "shading"},
            # ... and from the same teacher trained on a 128-light stage (``shading_l128``:
            # same poses, cameras and env maps; the student distills on this capture)
            "linear_tl128": {"head": "linear", "env_augment": "paper",
                             "teacher": "shading_l128"},
            # ... and from the same teacher trained on a capture with a key pose every
            # frame (``shading_k1``: other training poses; the student distills on that
            # capture's poses, so it sees them too)
            "linear_tk1": {"head": "linear", "env_augment": "paper",
                           "teacher": "shading_k1"}}
BASE = "tied"
#: what each variant is compared with (paired by seed): the students with ``tied`` (the
#: paper's text), DRAM with synthesized env maps with DRAM on the training maps alone
BASES = {"untied": BASE, "mix": BASE, "untied_mix": BASE, "dram_mix": "dram", "tied_8k": BASE,
         "linear": BASE, "linear_lsq": BASE, "lsq": BASE, "linear_8k": "tied_8k",
         "linear_tshading": "linear", "linear_tl128": "linear_tshading",
         "linear_tk1": "linear_tshading", "dram": "dram_eq11",
         "dram_b8": "dram", "dram_tex": "dram", "dram_tex_b8": "dram",
         "dram_tex_b8_mix": "dram_tex_b8", "linear_tex": "linear",
         "linear_mix": "linear"}
#: what the table compares: (split, reference), in order
SPLITS = ("heldout_pose_eval_env", "heldout_pose_train_env", "train_pose_eval_env",
          "ground_truth", "ground_truth_texels")
#: the splits scored against the stage's ground truth (a reference every variant shares):
#: the capture's own env renders (``distill``'s ``vs_ground_truth``, per vertex on the
#: converged capture) and the same capture's env renders made again as the stage shades
#: its LEDs (``eval_env_space: texels``, study_env_truth.py), the consistent truth
TRUTHS = ("ground_truth", "ground_truth_texels")
#: samples of the subsampled splits
SUBSAMPLE = 128


def _env_specs():
    import study_hands as S
    return S.env_specs()


def _prefill(teacher: str, capture: str, cache: str, part: int, parts: int) -> int:
    """Compute (or find) the teacher's per-direction textures of every pair a student of
    this capture samples or is scored on, every ``parts``-th from ``part``."""
    import torch

    torch.set_num_threads(1)
    data, targets = _targets(teacher, capture, cache)
    pairs = sorted(set(_train_pairs(data)) | set(_heldout_pairs(data)))
    for i, (pose, cam) in enumerate(pairs):
        if i % parts == part:
            targets.textures(pose, cam, False)
    return targets.computed


def _targets(teacher: str, capture: str, cache: str | None, grid=None):
    """(CaptureData, TeacherTargets) of the ``teacher`` checkpoint on ``capture``, its
    pseudo ground truth on the env grid ``grid`` (H, W; default the cpu preset's)."""
    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.inputs import load_envmap
    from relight_cli.jobs import distill as job
    from relight_cli.neural import distill as DI
    from relight_cli.neural.config import STUDENT_PRESETS
    from relight_cli.provenance import file_sha256
    sys.path.insert(0, str(P.HERE.parent))
    from commands import _learned as L
    tck = job.load_teacher(read_checkpoint(teacher, kind="teacher"), "cpu",
                           file_sha256(teacher), teacher)
    data = L.read_captures([capture], tck.config)[0]
    grid = discretize_env(load_envmap("builtin:uniform"),
                          *(grid or STUDENT_PRESETS["cpu"]["env_res"]))
    return data, DI.TeacherTargets(tck.net, tck.config, data, grid, cache, 0, "cpu",
                                   tck.mean_texture, identity=tck.identity)


def teacher_of(variant: str) -> str:
    """The study_teacher_inputs.py variant whose teacher a student variant distills
    (``VARIANTS[v]["teacher"]``, a study key, not a config field; default ``paper``)."""
    return VARIANTS[variant].get("teacher", "paper")


def student_config(variant: str) -> dict:
    return {k: v for k, v in VARIANTS[variant].items() if k != "teacher"}


def capture_of(variant: str, default: Path, stages: dict) -> Path:
    """The capture a student variant distills on and is scored on against its teacher:
    its teacher's stage's (``stages``: teacher variant → capture) when that stage moves
    the hand through other poses (:func:`study_teacher_inputs.moves`), else ``default``
    (other stages have the same poses, cameras and env maps)."""
    teacher = teacher_of(variant)
    return stages[teacher] if T.moves(T.STAGES.get(teacher, {})) else default


def textures_dir(work: Path, teacher: str, seed: int) -> Path:
    """Where the teacher's per-direction textures of one seed are cached."""
    return work / (f"textures_s{seed}" if teacher == "paper" else f"textures_{teacher}_s{seed}")


def _train_pairs(data) -> list:
    frames = data.train_frames + data.train_fully_lit_frames
    cams = [c.name for c in data.capture.cameras]
    return [(p, c) for p in sorted({f.pose for f in frames}) for c in cams]


def _heldout_pairs(data) -> list:
    return [(f.pose, cam) for f in data.heldout_frames for cam in f.images]


def _run(work: Path, capture: Path, teacher: Path, variant: str, seed: int, log) -> dict:
    """One student (cached): {"argv", "wall_s", "metrics"}."""
    name = f"{variant}_s{seed}"
    done = work / f"{name}.done.json"
    if done.is_file():
        return json.loads(done.read_text())
    config = work / f"{variant}.json"
    P.B_write(config, {**student_config(variant), "cache_mb": 0})
    envs = _env_specs()
    argv = ["distill", str(teacher), str(capture)]
    for spec in envs["train"]:
        argv += ["--envs", spec]
    for spec in envs["eval"]:
        argv += ["--eval-envs", spec]
    argv += ["--preset", "cpu", "--config", str(config), "--seed", str(seed), "--cache",
             str(textures_dir(work, teacher_of(variant), seed)), "-o", str(work / f"{name}.pt"),
             "--metrics-out", str(work / f"{name}.json"), "-q"]
    return T.run_once(work, name, argv, "study_student_env.py", log)


def _student_task(work: Path, capture: Path, teacher: Path, variant: str, seed: int,
                  specs: list, n_train: int):
    """(model, CaptureData, TeacherTargets, env grids of ``specs``, StudentTask) of one
    run's checkpoint, its first ``n_train`` maps the training maps."""
    from relight_cli.envmap import discretize_env
    from relight_cli.formats.checkpoint import read_checkpoint
    from relight_cli.inputs import load_envmap
    from relight_cli.neural import distill as DI
    from relight_cli.neural.checkpoints import student_model
    name = f"{variant}_s{seed}"
    model, config = student_model(read_checkpoint(str(work / f"{name}.pt"), kind="student"))
    data, targets = _targets(str(teacher), str(capture),
                             str(textures_dir(work, teacher_of(variant), seed)))
    grids = [discretize_env(load_envmap(s), *config.env_res) for s in specs]
    task = DI.StudentTask(data, config, targets, grids, list(range(n_train)),
                          list(range(n_train, len(specs))), specs)
    return model, data, targets, grids, task


def _score(work: Path, capture: Path, teacher: Path, variant: str, seed: int) -> dict:
    """The checkpoint against its teacher on the study's splits (cached):
    {split: {"mse", "psnr", "ssim", "samples"}}."""
    name = f"{variant}_s{seed}"
    path = work / f"{name}.all.json"
    if path.is_file():
        return json.loads(path.read_text())
    import numpy as np
    import torch

    from relight_cli.neural.train import _metrics
    envs = _env_specs()
    specs = envs["train"] + envs["eval"]
    n_train = len(envs["train"])
    model, data, targets, grids, task = _student_task(work, capture, teacher, variant, seed,
                                                      specs, n_train)
    held, train = _heldout_pairs(data), _train_pairs(data)
    combos = {"heldout_pose_eval_env": [(p, c, e) for p, c in held
                                        for e in range(n_train, len(specs))],
              "heldout_pose_train_env": [(p, c, e) for p, c in held for e in range(n_train)],
              "train_pose_eval_env": [(p, c, e) for p, c in train
                                      for e in range(n_train, len(specs))]}
    out = {}
    for split, items in combos.items():
        if split != "heldout_pose_eval_env" and len(items) > SUBSAMPLE:
            pick = np.unique(np.linspace(0, len(items) - 1, SUBSAMPLE).round().astype(int))
            items = [items[i] for i in pick]
        rows = []
        for pose, cam, e in items:
            with torch.no_grad():
                pred = task.render(model, pose, cam, grids[e], "cpu").numpy()
            gt = targets.image(pose, cam, grids[e]).numpy()
            m = _metrics(pred, gt, data.gbuffer(pose, data._cameras[cam]).mask)
            if m:
                rows.append(m)
        out[split] = {k: float(np.mean([r[k] for r in rows])) for k in ("mse", "psnr", "ssim")}
        out[split]["samples"] = len(rows)
    P.B_write(path, out)
    return out


#: DRAM's light response: training (pose, camera) pairs (evenly spaced) and rotations (in
#: longitude steps) of each training map; 4 × 7 maps × 3 = 84 textures per run
LIGHT_PAIRS, LIGHT_ROTATIONS = 4, (0, 5, 10)


def _light(work: Path, capture: Path, teacher: Path, variant: str, seed: int) -> dict:
    """Whether a DRAM run's light path trained (cached): at ``LIGHT_PAIRS`` training
    (pose, camera) pairs, its texture and the teacher's (first hand, ÷ s, over the UV
    charts' texels) under every training map at each of ``LIGHT_ROTATIONS``; the
    variation over these lightings of each, centred per texel: the mean per-texel
    standard deviation of each (``std``, ``teacher_std``), their correlation (``corr``)
    and the share of the teacher's variation DRAM's explains, 1 − |a − b|²/|b|²
    (``explained``; a light path that does not train: ≈ 0)."""
    name = f"{variant}_s{seed}"
    path = work / f"{name}.light.json"
    if path.is_file():
        return json.loads(path.read_text())
    import numpy as np
    import torch

    from relight_cli.neural import distill as DI
    torch.set_num_threads(1)
    specs = _env_specs()["train"]
    model, data, targets, grids, task = _student_task(work, capture, teacher, variant, seed,
                                                      specs, len(specs))
    pairs = _train_pairs(data)
    pick = np.unique(np.linspace(0, len(pairs) - 1, LIGHT_PAIRS).round().astype(int))
    inside = task.chart_mask("cpu")[0, 0]
    rows = []
    for pose, cam in (pairs[i] for i in pick):
        ours, theirs = [], []
        for grid in grids:
            for steps in LIGHT_ROTATIONS:
                denv = DI.rotate_env(grid, steps) if steps else grid
                s = DI.env_scale(denv)
                with torch.no_grad():
                    ours.append(task.textures(model, pose, cam, denv, "cpu")[0][0][:, inside]
                                / s)
                theirs.append(targets.texture(pose, cam, denv)[0][:, inside] / s)
        a, b = (torch.stack(x).double() for x in (ours, theirs))
        a, b = a - a.mean(0), b - b.mean(0)
        rows.append([float(a.std(0).mean()), float(b.std(0).mean()),
                     float((a * b).sum() / max(float(a.norm() * b.norm()), 1e-30)),
                     float(1 - (a - b).pow(2).sum() / b.pow(2).sum())])
    out = dict(zip(("std", "teacher_std", "corr", "explained"),
                   (float(v) for v in np.mean(rows, 0))))
    out["pairs"] = len(rows)
    P.B_write(path, out)
    return out


def is_dram(variant: str) -> bool:
    return VARIANTS[variant].get("student") == "dram"


def _seed_row(record: dict, scores: dict, texels: dict) -> dict:
    m = record["metrics"]["metrics"]
    gt = m["vs_ground_truth"]
    row = {"wall_s": record["wall_s"], **scores,
           "ground_truth": {"mse": gt["mse"], "psnr": gt["psnr"], "ssim": gt["ssim"],
                            "samples": gt["samples"], "ceiling": gt["ceiling"]["psnr"],
                            "ceiling_mse": gt["ceiling"]["mse"], "gap": gt["gap_to_ceiling"]},
           "ground_truth_texels": texels,
           "validation_vs_teacher": m["vs_teacher"]}
    curve = P._curve(record, "vs_teacher")
    iters = curve[-1][0]
    row["closed_form"] = iters == 0           # ``lsq`` at 0 iterations: nothing to converge
    tail = [(s, v) for s, v in curve if (1 - P.TAIL) * iters <= s < iters]
    if not tail:    # validation sparser than the tail: the last interval before the end
        tail = [(s, v) for s, v in curve if s < iters][-1:]
    row["gain_tail_db"] = curve[-1][1] - tail[0][1] if tail else None
    row["tail_from"] = tail[0][0] if tail else None
    row["curve"] = curve
    return row


def summarize(runs: dict) -> dict:
    """Per variant: per-seed rows, mean ± std of each split's PSNR and MSE, convergence;
    per variant with a base in :data:`BASES` and split: the paired PSNR difference from
    the base and the verdict."""
    out = {}
    for variant, rows in runs.items():
        entry = {"seeds": rows}
        for split in SPLITS:
            entry[split] = {"psnr": T._stats([r[split]["psnr"] for r in rows]),
                            "mse": T._stats([r[split]["mse"] for r in rows])}
        for split in TRUTHS:
            entry[split]["gap"] = T._stats([r[split]["gap"] for r in rows])
            entry[split]["ceiling"] = rows[0][split]["ceiling"]
            entry[split]["ceiling_mse"] = rows[0][split]["ceiling_mse"]
        gains = [r["gain_tail_db"] for r in rows]
        entry["converged"] = all(r.get("closed_form") or (g is not None and g < P.CONVERGED_DB)
                                 for r, g in zip(rows, gains))
        entry["wall_min"] = sum(r["wall_s"] for r in rows) / 60
        if all("light" in r for r in rows):
            entry["light"] = {k: T._stats([r["light"][k] for r in rows])
                              for k in ("std", "teacher_std", "corr", "explained")}
        out[variant] = entry
    for variant, rows in runs.items():
        base = runs.get(BASES.get(variant))
        if base is None:
            continue
        out[variant]["versus"] = {"base": BASES[variant], "splits": {}}
        for split in SPLITS:
            if split not in TRUTHS and teacher_of(variant) != teacher_of(BASES[variant]):
                continue        # against two different teachers: no common reference
            mean, std = T._stats([a[split]["psnr"] - b[split]["psnr"]
                                  for a, b in zip(rows, base)])
            ratio = T._stats([a[split]["mse"] / b[split]["mse"] for a, b in zip(rows, base)])
            margin = max(2 * std, 0.2)
            verdict = "better" if mean > margin else "worse" if mean < -margin else "tie"
            out[variant]["versus"]["splits"][split] = {
                "diff_db": mean, "std_db": std, "margin_db": margin, "verdict": verdict,
                "mse_ratio": ratio[0]}
    return out


def main(argv=None) -> None:
    ap = B.parser(__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(B.OUT / "student_env"), metavar="DIR",
                    help="cache: the students, the teachers' textures, scores")
    ap.add_argument("--teachers", default=str(B.OUT / "teacher_inputs"), metavar="DIR",
                    help="study_teacher_inputs.py's cache: the paper-input teachers")
    args, variants = T.parse_variants(ap, argv, VARIANTS, ",".join(VARIANTS), 2,
                                      "student (minutes); tests/test_neural_student.py "
                                      "covers the options themselves")
    out = B.start(args, "study_student_env.py")
    work, teachers = Path(args.work), Path(args.teachers)
    work.mkdir(parents=True, exist_ok=True)
    teachers.mkdir(parents=True, exist_ok=True)

    def log(m):
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    limits = B.machine_limits()
    capture, _ = P._capture(teachers, log)
    seeds = list(range(args.seeds))
    workers = max(1, args.workers)
    kinds = sorted({teacher_of(v) for v in variants})
    # each teacher trains on its own stage's capture (T.STAGES); the students distill on
    # the converged one (the same poses, cameras and env maps on every stage)
    stage = {t: P._capture(teachers, log, stage=T.STAGES.get(t))[0] for t in kinds}
    with ThreadPoolExecutor(workers) as pool:      # the teachers (cached)
        list(pool.map(lambda job: T._run(teachers, stage[job[0]], *job, log),
                      [(t, s) for t in kinds for s in seeds]))
    teacher = {(t, s): teachers / f"{t}_s{s}.pt" for t in kinds for s in seeds}
    on = {v: capture_of(v, capture, stage) for v in variants}
    where_of = {teacher_of(v): on[v] for v in variants}
    for t, s in teacher:
        where = textures_dir(work, t, s)
        marker = where.parent / f"{where.name}.done"
        if not marker.is_file():
            log(f"{t} teacher seed {s}: its per-direction textures, {workers} process(es)")
            where.mkdir(exist_ok=True)
            with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
                list(pool.map(_prefill, *zip(*[(str(teacher[t, s]), str(where_of[t]),
                                                str(where), k, workers)
                                               for k in range(workers)])))
            marker.write_text("done\n")
    jobs = [(v, s) for s in seeds for v in variants]
    with ThreadPoolExecutor(workers) as pool:
        records = list(pool.map(
            lambda job: _run(work, on[job[0]], teacher[teacher_of(job[0]), job[1]], *job, log),
            jobs))
    # spawned, not forked: a child forked from this process (its threads above, torch's
    # thread pools) deadlocked before scoring anything (seen: 1 h 40 min idle)
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        scores = list(pool.map(_score, *zip(*[(work, on[v], teacher[teacher_of(v), s], v, s)
                                              for v, s in jobs])))
    # the consistent env truth: the same capture made again with its env renders shaded
    # as its LEDs (identical LED frames; study_env_truth.py)
    import study_env_truth as ET
    texels = P._capture(teachers, log, stage=ET.stage_of("", "texels"))[0]
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        consistent = list(pool.map(ET.score_student, *zip(*[
            (str(work), str(teachers), str(texels), v, s, "texels") for v, s in jobs])))
    runs = {v: [_seed_row(r, sc, tx) for (vv, _), r, sc, tx
                in zip(jobs, records, scores, consistent) if vv == v] for v in variants}
    lit = [(v, s) for v, s in jobs if is_dram(v)]
    if lit:                 # whether DRAM's light path trained, per run
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            light = list(pool.map(_light, *zip(*[(work, on[v], teacher[teacher_of(v), s],
                                                  v, s) for v, s in lit])))
        for (v, s), value in zip(lit, light):
            runs[v][seeds.index(s)]["light"] = value
    record = {"command": B.run_command("study_student_env.py",
                                       sys.argv[1:] if argv is None else argv),
              "machine": limits, "capture": str(capture), "seeds": seeds,
              "captures": {v: str(on[v]) for v in variants if on[v] != capture},
              "envs": _env_specs(), "wall_s": round(time.perf_counter() - t0, 1),
              "variants": {v: VARIANTS[v] for v in variants},
              "by_hand": {f"{v}_s{s}": r["note"] for (v, s), r in zip(jobs, records)
                          if r.get("note")},
              "results": summarize(runs)}
    import study_hands as S
    record = S.portable(record)     # committed tables name no machine's folders
    P.B_write(out / "student_env.json", record)
    (out / "student_env.md").write_text(_markdown(record))
    _plot(record, out / "student_env.png")
    print((out / "student_env.md").read_text())


#: what a variant studies (the table's title)
TOPICS = {"untied": "per-texel biases", "mix": "synthesized env maps",
          "untied_mix": "per-texel biases and synthesized env maps", "dram": "DRAM",
          "dram_mix": "DRAM", "dram_b8": "DRAM", "dram_tex": "DRAM", "dram_tex_b8": "DRAM",
          "dram_tex_b8_mix": "DRAM",
          "tied_8k": "training length",
          "linear": "a head linear in its features", "linear_lsq": "a head linear in its features",
          "lsq": "a head linear in its features", "linear_8k": "a head linear in its features",
          "linear_tshading": "a teacher with shading features as input",
          "linear_tl128": "that teacher on a 128-light stage",
          "linear_tk1": "that teacher and the student on a capture of more poses",
          "linear_tex": "the loss on whole textures",
          "linear_mix": "synthesized env maps"}

NAMES = {"heldout_pose_eval_env": "held-out poses × held-out maps",
         "heldout_pose_train_env": "held-out poses × training maps",
         "train_pose_eval_env": "trained poses × held-out maps",
         "ground_truth": "ground truth: held-out poses × held-out maps",
         "ground_truth_texels": "consistent ground truth (texels): held-out poses × "
                                "held-out maps"}


def _markdown(record: dict) -> str:
    res = record["results"]
    # records made before the consistent truth have its splits' predecessors only
    splits = [s for s in SPLITS if s in next(iter(res.values()))]
    rows_min = sum(v["wall_min"] for v in res.values())
    envs = record["envs"]
    topics = []
    for v in record["variants"]:
        topic = TOPICS.get(v)
        if topic and topic not in topics:
            topics.append(topic)
    lines = ["# The converged student: " + " and ".join(topics or ["the paper's text"]), "",
             f"Command: `{record['command']}`  ",
             B.machine_line(record["machine"]) + "  ",
             f"Wall time: {record['wall_s'] / 60:.1f} min for this invocation (runs in its "
             f"cache cost nothing); the students themselves took {rows_min:.1f} min, one core "
             f"each, two at a time; seeds {', '.join(map(str, record['seeds']))}; right "
             f"hand, `converged` capture, `--preset cpu`, each seed's "
             + ", ".join(sorted({f"`{v.get('teacher', 'paper')}`" for v in
                                 record["variants"].values()}))
             + "-input OLAT teacher (study_teacher_inputs.py; a variant's `teacher` names "
             f"its own); {len(envs['train'])} training env maps "
             f"({', '.join(Path(s.split(':', 1)[-1]).stem for s in envs['train'])}), "
             f"held out: {', '.join(Path(s).stem for s in envs['eval'])}."
             + (" Runs by hand (their cached records say how): "
                + "; ".join(f"{k}: {v}" for k, v in record["by_hand"].items()) + "."
                if record.get("by_hand") else ""), "",
             "MSE ×10⁻³ (mean over seeds ± std) against the teacher, then against the "
             "ground truth with its gap to the ceiling"
             + (" (the capture's env renders, made per vertex; then the same capture's env "
                "renders shaded as its LEDs, `eval_env_space: texels`: the consistent "
                "truth, study_env_truth.py):" if len(splits) > 4 else ":"), "",
             "| variant | " + " | ".join(NAMES[s] for s in splits[:4]) + " | gap to ceiling "
             "(dB) | " + "".join(f"{NAMES[s]} | gap (dB) | " for s in splits[4:])
             + "converged | min per run |", "|---" * (len(splits) + 4 + len(splits[4:]))
             + "|"]
    for v, e in res.items():
        cells = [f"{e[s]['mse'][0] * 1e3:.2f} ± {e[s]['mse'][1] * 1e3:.2f}" for s in splits]
        gaps = [f"{e[s]['gap'][0]:.2f} ± {e[s]['gap'][1]:.2f}" for s in splits[3:]]
        gains = ", ".join("closed form" if r.get("closed_form") else "?"
                          if r["gain_tail_db"] is None else f"{r['gain_tail_db']:+.2f}"
                          for r in e["seeds"])
        lines.append(f"| {v} ({json.dumps(record['variants'][v])}) | "
                     + " | ".join(cells[:4] + [gaps[0]] + [c for pair in zip(cells[4:], gaps[1:])
                                                           for c in pair])
                     + f" | {'yes' if e['converged'] else 'NOT'} ({gains}) | "
                     f"{e['wall_min'] / len(e['seeds']):.1f} |")
    first = next(iter(res.values()))
    ceilings = [f"{first[s]['ceiling_mse'] * 1e3:.2f}" for s in splits[3:]]
    lines += ["| ceiling (perfect texture) | | | | " + " | | ".join(ceilings) + " | | | |",
              "", "Mean PSNR (dB) per split; "
              + (", ".join(f"`{v}` against `{e['versus']['base']}`"
                           for v, e in res.items() if e.get("versus")) or "no comparisons")
              + ", paired by seed (verdict when |difference| > max(2 σ, 0.2 dB)), with the "
              "mean MSE ratio (a student of another teacher only against the ground truth, "
              "the reference both share):", ""]
    for v, e in res.items():
        lines.append(f"- {v}: " + "; ".join(
            f"{NAMES[s]} {e[s]['psnr'][0]:.2f} ± {e[s]['psnr'][1]:.2f}" for s in splits))
        versus = e.get("versus") or {"splits": {}}
        for s, d in versus["splits"].items():
            lines.append(f"  - vs {versus['base']}, {NAMES[s]}: {d['diff_db']:+.2f} ± "
                         f"{d['std_db']:.2f} dB, MSE × {d['mse_ratio']:.2f} → "
                         f"**{d['verdict']}**")
    lit = {v: e for v, e in res.items() if e.get("light")}
    if lit:
        lines += ["", "Whether DRAM's light path trained: at "
                  f"{LIGHT_PAIRS} training (pose, camera) pairs, its texture and the teacher's "
                  f"under each training map at {len(LIGHT_ROTATIONS)} rotations (÷ s, UV "
                  "charts' texels), centred per texel over these lightings: per-texel "
                  "standard deviation (the teacher's beside it), correlation with the "
                  "teacher's, and the share of the teacher's variation explained, "
                  "1 − |a − b|²/|b|² (≈ 0: a light path that does not train); mean ± std "
                  "over seeds, then each seed's share:", "",
                  "| variant | std (teacher) | correlation | explained | per seed |",
                  "|---|---|---|---|---|"]
        for v, e in lit.items():
            g = e["light"]
            lines.append(f"| {v} | {g['std'][0]:.3f} ± {g['std'][1]:.3f} "
                         f"({g['teacher_std'][0]:.3f}) | {g['corr'][0]:.2f} ± "
                         f"{g['corr'][1]:.2f} | {g['explained'][0]:.2f} ± "
                         f"{g['explained'][1]:.2f} | "
                         + ", ".join(f"{r['light']['explained']:.2f}" for r in e["seeds"])
                         + " |")
    lines += ["", f"Samples: every held-out (frame, camera) × each held-out map; {SUBSAMPLE} "
              "evenly spaced samples of the other two teacher splits; every held-out env "
              "render of the capture for the ground truth (the ceiling: the perfect texture "
              "at the student's N through the same compositing). Converged: every seed's "
              "validation PSNR against the teacher gained < 0.2 dB over the last 20 % of its "
              "iterations (over the last validation interval where validation is sparser: "
              "25 % at the `cpu` preset's 1,000 of 4,000); the column gives each seed's gain "
              "(dB). Plot: student_env.png.", ""]
    return "\n".join(lines)


def _plot(record: dict, path: Path) -> None:
    fig, (ax,) = B.figure()
    T.plot_seed_curves(ax, record)
    ax.set_xlabel("iteration")
    ax.set_ylabel("validation PSNR against the teacher (dB)")
    topics = sorted({TOPICS[v] for v in record["variants"] if v in TOPICS})
    import textwrap
    ax.set_title(textwrap.fill("student, cpu preset: " + (", ".join(topics)
                                                          or "the paper's text")
                               + " (one line per seed)", 70), fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend()
    B.save(fig, path, record["machine"])


if __name__ == "__main__":
    main()
