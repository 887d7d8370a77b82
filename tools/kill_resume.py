"""Kill a training run and resume it: the result must be the uninterrupted run's, bit for bit.

    .venv/bin/python tools/kill_resume.py --out /tmp/kr [--trials 6] [--seed 0]

For ``train-teacher`` and ``distill`` (tiny configs, periodic saves every 4 steps) this
trains once uninterrupted, then per trial starts the same command and sends SIGKILL or
SIGTERM (alternating) at one of three moments once a first checkpoint exists: a random
time, while a later checkpoint is being written (the moment its temporary file
appears), and right after a save (the moment the output's mtime changes).  It then checks that the output is absent or a
loadable checkpoint (a SIGKILL mid-write may leave the killed write's temporary file,
named for the output and removed by the next write to it; it is reported), resumes
with ``--resume OUTPUT`` into another file (or restarts when nothing was saved), and compares the final
weights, optimizer state and step with the uninterrupted run's (``cmp`` of the state,
since the provenance's command line differs).  Prints one line per trial and exits 1 on
any difference.  A check of issue 23's guarantees, run by hand (minutes), not by
``make test``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

RELIGHT = [str(Path(sys.executable).parent / "relight")]   # the installed console script
ITERS = 40
TEACHER = {"tex_res": 16, "encoder": [4, 4, 4], "decoder": [8, 8, 8], "pose_channels": [4, 4],
           "val_samples": 1, "aa": 1, "save_every": 4}
STUDENT = {"tex_res": 16, "decoder": [8, 8, 8, 8, 8, 8, 8], "pose_channels": [4, 8],
           "val_samples": 1, "env_holdout": 0.34, "env_res": [4, 8], "cache_mb": 0,
           "save_every": 4}
ENVS = ["--envs", "builtin:sky", "--envs", "builtin:studio", "--envs", "builtin:uniform"]


def _run(args, **kw):
    return subprocess.run(RELIGHT + [str(a) for a in args], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, **kw)


def _state(path):
    import torch
    ck = torch.load(path, weights_only=True)
    return {k: ck[k] for k in ("weights", "optimizer", "step", "rng") if k in ck}


def _same(a, b) -> bool:
    import torch
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and \
            bool(torch.equal(a, b))
    return a == b


def _temps(folder: Path):
    return sorted(p.name for p in folder.iterdir() if "relight-tmp" in p.name)


def _kill_at(cmd, out: Path, moment: str, sig, rng) -> str:
    """Start ``cmd``; send ``sig`` at ``moment``; return what happened."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(RELIGHT + [str(a) for a in cmd], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=env)
    start, deadline = time.monotonic(), time.monotonic() + 300
    delay = rng.uniform(0.0, 1.5)
    mtime = None
    first = None        # when the first periodic save appeared
    while proc.poll() is None and time.monotonic() < deadline:
        if first is None and out.exists():
            first = time.monotonic()
        if moment == "random" and first is not None and time.monotonic() - first > delay:
            break
        if moment == "during-save" and first is not None and _temps(out.parent):
            break
        if moment == "after-save" and out.exists():
            m = out.stat().st_mtime_ns
            if mtime is not None and m != mtime:
                break
            mtime = m
        time.sleep(0.002)
    if proc.poll() is not None:
        return "finished before the signal"
    proc.send_signal(sig)
    proc.wait()
    return f"{signal.Signals(sig).name} at {moment} (exit {proc.returncode})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--trials", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rng = random.Random(a.seed)
    cap = a.out / "cap"
    if not (cap / "capture.json").exists():
        r = _run(["synth-capture", "-o", cap, "--cameras", "2", "--leds", "6", "--group", "2",
                  "--n-frames", "4", "--size", "16", "--tex-res", "32", "--aa", "1",
                  "--eval-poses", "1", "--eval-cameras", "1", "--eval-envs", "builtin:sky",
                  "--eval-env-res", "16x8", "-q"])
        assert r.returncode == 0, r.stderr
    (a.out / "teacher.json").write_text(json.dumps(TEACHER))
    (a.out / "student.json").write_text(json.dumps(STUDENT))
    teacher_ref = a.out / "teacher_ref.pt"
    jobs = {
        "train-teacher": lambda o: ["train-teacher", cap, "--iters", ITERS, "-q", "-o", o],
        "distill": lambda o: ["distill", teacher_ref, cap, *ENVS, "--iters", ITERS, "-q",
                              "-o", o],
    }
    configs = {"train-teacher": ["--config", a.out / "teacher.json"],
               "distill": ["--config", a.out / "student.json"]}
    failures = 0
    for job, make in jobs.items():
        ref = a.out / f"{job}_ref.pt" if job != "train-teacher" else teacher_ref
        if not ref.exists():
            r = _run(make(ref) + configs[job])
            assert r.returncode == 0, r.stderr
        want = _state(ref)
        for trial in range(a.trials):
            folder = a.out / f"{job}_{trial}"
            folder.mkdir(exist_ok=True)
            for p in folder.iterdir():
                p.unlink()
            out = folder / "o.pt"
            moment = ("random", "during-save", "after-save")[trial % 3]
            sig = (signal.SIGKILL, signal.SIGTERM)[trial % 2]
            what = _kill_at(make(out) + configs[job], out, moment, sig, rng)
            saved = out.exists()
            if saved:
                try:
                    step = int(_state(out)["step"])
                except Exception as exc:      # noqa: BLE001 - a damaged checkpoint is the failure
                    print(f"FAIL {job} trial {trial}: {what}: output not loadable: {exc}")
                    failures += 1
                    continue
            final = folder / "resumed.pt"       # an output may not be an input
            # a resumed run takes the checkpoint's own configuration
            r = _run(make(final) + (["--resume", out] if saved else configs[job]))
            stale = [t for t in _temps(folder) if "o.pt" in t]    # SIGKILL mid-write
            ok = r.returncode == 0 and _same(_state(final), want) and \
                not [t for t in _temps(folder) if "resumed.pt" in t]
            failures += not ok
            print(f"{'ok  ' if ok else 'FAIL'} {job} trial {trial}: {what}; "
                  f"{'resumed from step ' + str(step) if saved else 'nothing saved: rerun'}; "
                  f"{'identical to the uninterrupted run' if ok else r.stderr.strip()[-300:]}"
                  + (f" (the killed write left {stale[0]})" if stale else ""),
                  flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
