"""Every benchmark script checks its paths before any work (issue 52, cause 9): an output
folder that is a file or cannot be made, a damaged JSON given to ``--report``, a
``--gate-spread`` file whose folder is missing give one line ``<script>: error: … (<path>)``,
exit 2 (usage) or 1 (data), no traceback and nothing created.  The scripts run in
subprocesses, all at once (each stops after its imports)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCH.glob("bench_*.py"))


def _run_all(cases: dict, cwd: Path) -> dict:
    """{key: argv} → {key: CompletedProcess-like (returncode, stdout, stderr)}, in parallel."""
    env = dict(os.environ, PYTHONWARNINGS="ignore", OMP_NUM_THREADS="1")
    procs = {k: subprocess.Popen([sys.executable, *map(str, argv)], cwd=cwd, env=env,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k, argv in cases.items()}
    done = {}
    for k, p in procs.items():
        try:
            out, err = p.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
            err += "\n(timed out: the check did not run before the work)"
        done[k] = subprocess.CompletedProcess(p.args, p.returncode, out, err)
    return done


def _one_line(r, script: str, code: int, *words: str) -> str:
    lines = r.stderr.splitlines()
    assert r.returncode == code, r.stderr[-2000:]
    assert len(lines) == 1, r.stderr[-2000:]
    assert lines[0].startswith(f"{script}: error: "), lines[0]
    assert "Traceback" not in r.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_every_benchmark_refuses_an_out_that_is_not_a_folder(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    cases = {}
    for script in SCRIPTS:
        cases[(script, "file")] = [BENCH / script, "--quick", "--out", a_file]
    for script in ("bench_envmap.py", "bench_hand.py"):     # (a path under a file: once)
        cases[(script, "under")] = [BENCH / script, "--quick", "--out", a_file / "sub"]
    for (script, kind), r in _run_all(cases, tmp_path).items():
        _one_line(r, script, 2, "--out", str(a_file))
    assert a_file.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]      # nothing created


def test_bench_presets_work_checked_before_out_is_made(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    r = _run_all({0: [BENCH / "bench_presets.py", "--quick", "--out", tmp_path / "new",
                      "--work", a_file]}, tmp_path)[0]
    _one_line(r, "bench_presets.py", 2, "--work", str(a_file))
    assert not (tmp_path / "new").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_out_is_refused(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        done = _run_all({s: [BENCH / s, "--quick", "--out", ro / "sub"] for s in
                         ("bench_envmap.py", "bench_hand.py")}, tmp_path)
        for script, r in done.items():
            _one_line(r, script, 2, "not writable")
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_damaged_reports_and_missing_folders(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "sequence.json").write_text('{"models": {"linear": ')
    results = tmp_path / "results"
    results.mkdir()
    (results / "study_rh_t13.json").write_text("{not json")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    cases = {
        "sequence": [BENCH / "bench_sequence.py", "--report", "--out", seq],
        "study_report": [BENCH / "study_hands.py", "--report", "--results", results,
                         "--tables", "rh_t13"],
        "gate_spread": [BENCH / "study_hands.py", "--out", tmp_path / "work",
                        "--gate-spread", tmp_path / "nodir" / "x.json"],
        "study_out": [BENCH / "study_hands.py", "--out", a_file],
        "study_results": [BENCH / "study_hands.py", "--out", tmp_path / "work2",
                          "--results", a_file],
    }
    done = _run_all(cases, tmp_path)
    _one_line(done["sequence"], "bench_sequence.py", 1, "damaged JSON", "sequence.json")
    _one_line(done["study_report"], "study_hands.py", 1, "damaged JSON", "study_rh_t13.json")
    _one_line(done["gate_spread"], "study_hands.py", 2, "--gate-spread", "nodir")
    _one_line(done["study_out"], "study_hands.py", 2, "--out", str(a_file))
    _one_line(done["study_results"], "study_hands.py", 2, "--results", str(a_file))
    assert not (tmp_path / "work").exists() and not (tmp_path / "work2").exists()
    assert not (tmp_path / "nodir").exists()
    assert sorted(p.name for p in results.iterdir()) == ["study_rh_t13.json"]


def test_readme_tables_damaged_record_is_one_line(tmp_path):
    bad = tmp_path / "presets.json"
    bad.write_text("[1, 2")
    code = ("import sys; sys.path.insert(0, %r); import readme_tables as R; "
            "import _common as B; B.run_main('readme_tables.py', R.presets, R.Path(%r))"
            % (str(BENCH), str(bad)))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    _one_line(r, "readme_tables.py", 1, "damaged JSON", str(bad))


#: bench_mitsuba.py is left out here: it is another engineer's, still being written
OPTION_SCRIPTS = [s for s in SCRIPTS if s != "bench_mitsuba.py"] + ["study_hands.py",
                                                                    "readme_tables.py"]


def test_bad_options_and_values_are_one_line_without_usage(tmp_path):
    """A bad option or value is argparse's error as one line ``<script>: error: …`` and
    exit 2, with no usage block before it (benchmarks/_common.ArgumentParser); an --env or
    --report record that is not there is one line and exit 1; nothing is created."""
    out = tmp_path / "o"
    cases = {(s, "unknown"): ([BENCH / s, "--no-such-option"], 2, ["unrecognized arguments",
                                                                   "--no-such-option"])
             for s in OPTION_SCRIPTS}
    bad = [("bench_splat.py", ["--n", "x"], "--n"), ("bench_splat.py", ["--size", "0"], "--size"),
           ("bench_hand.py", ["--frames", "5,x"], "--frames"),
           ("bench_features.py", ["--ref-env-res", "128"], "--ref-env-res"),
           ("bench_features.py", ["--pose", "wave"], "--pose"),
           ("bench_features.py", ["--res", "-1"], "--res"),
           ("bench_sequence.py", ["--budget", "nan"], "--budget"),
           ("bench_sequence.py", ["--frames", "0"], "--frames"),
           ("bench_sequence.py", ["--models", "nope"], "nope"),
           ("bench_student.py", ["--threads", "0"], "--threads"),
           ("bench_teacher.py", ["--iters", "0"], "--iters"),
           ("bench_linear.py", ["--iters", "x"], "--iters"),
           ("bench_dgsm.py", ["--occluder", "cube"], "--occluder"),
           ("bench_dgsm.py", ["--scenes", "hand:wave"], "--scenes"),
           ("bench_dgsm.py", ["--speed-seeds", "0"], "--speed-seeds"),
           ("bench_dgsm_lighting.py", ["--clips", "nope"], "--clips"),
           ("bench_dgsm_lighting.py", ["--frames", "1"], "--frames"),
           ("study_hands.py", ["--seeds", "0"], "--seeds"),
           ("study_hands.py", ["--tables", "nope"], "nope"),
           ("study_hands.py", ["--workers", "-1"], "--workers")]
    for i, (script, argv, word) in enumerate(bad):
        quick = [] if script == "study_hands.py" else ["--quick"]      # (it has --scale)
        cases[(script, i)] = ([BENCH / script, *quick, "--out", out, *argv], 2, [word])
    cases[("study_hands.py", "no out")] = ([BENCH / "study_hands.py"], 2, ["--out"])
    cases[("bench_features.py", "env")] = ([BENCH / "bench_features.py", "--quick", "--out", out,
                                            "--env", tmp_path / "none.exr"], 1,
                                           ["--env", "no such file", "none.exr"])
    cases[("study_hands.py", "report")] = ([BENCH / "study_hands.py", "--report", "--results",
                                            tmp_path, "--tables", "rh_t13"], 1,
                                           ["study_rh_t13.json", "run the table first"])
    done = _run_all({k: argv for k, (argv, _, _) in cases.items()}, tmp_path)
    for key, (argv, code, words) in cases.items():
        r = done[key]
        assert "usage:" not in r.stderr, (key, r.stderr)
        _one_line(r, key[0], code, *words)
    assert list(tmp_path.iterdir()) == []                              # nothing created


def test_help_is_still_argparse_usage():
    """``--help`` keeps argparse's own behaviour: the usage and options on stdout, exit 0."""
    r = _run_all({0: [BENCH / "bench_splat.py", "--help"]}, BENCH)[0]
    assert r.returncode == 0 and r.stderr == ""
    assert r.stdout.startswith("usage: bench_splat.py") and "--quick" in r.stdout
