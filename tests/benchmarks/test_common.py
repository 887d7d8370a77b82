"""benchmarks/_common.py: the missing-matplotlib line, the shared options, the plot helper,
the studies' captures; bench_presets.py's rows; what the scripts may import.  (The rules
the benchmarks judge by are relight_cli.neural.judging's: tests/neural/test_judging.py.)"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
import _common as B  # noqa: E402


def test_a_runner_without_matplotlib_stops_with_one_line(tmp_path):
    code = ("import sys; sys.modules['matplotlib'] = None; sys.argv = ['bench_envmap.py', "
            f"'--quick', '--out', {str(tmp_path / 'out')!r}]; import runpy; "
            f"runpy.run_path({str(BENCH / 'bench_envmap.py')!r}, run_name='__main__')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert r.stderr.strip() == ("bench_envmap.py: error: matplotlib is not installed; pip install "
                                "'relight[bench]' (make benchmarks does)")
    assert not (tmp_path / "out").exists()           # stopped before any work


def test_every_benchmark_takes_out_and_quick():
    for script in sorted(BENCH.glob("bench_*.py")):
        text = script.read_text()
        assert "B.parser(" in text and "B.start(" in text, script.name
        assert "machine_limits(" in text, script.name


def test_options_and_machine_line():
    args = B.parser("doc").parse_args(["--quick", "--out", "x"])
    assert args.quick and args.out == "x"
    assert B.parser("doc").parse_args([]).out == str(B.OUT)
    line = B.machine_line({"platform": "p", "cpus": 2, "load_average": "1 1 1", "gemm_gflops": 10.0,
                           "memory_gbs": 5.0, "embree_mrays": 1.5})
    assert "fp32 GEMM 10.0 GFLOP/s" in line and "embree 1.50 Mrays/s" in line


def test_plot_draws_every_curve_including_exact_and_nonfinite_points(tmp_path):
    pytest.importorskip("matplotlib")
    B.require_matplotlib("test")
    fig, (ax,) = B.figure(1)
    B.plot(ax, {"a": [(1.0, 0.1, "x"), (2.0, 0.0, "exact"), (3.0, float("nan"))],
                "b": [(0.5, 1e-3), (4.0, 1e-4)], "empty": []}, "seconds", "error")
    names = [t.get_text() for t in ax.get_legend().get_texts()]
    assert names == ["a", "exact (0)", "b"]
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    path = B.save(fig, tmp_path / "p.png", {"platform": "p", "cpus": 2, "load_average": "0",
                                            "gemm_gflops": 1.0, "memory_gbs": 1.0})
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


#: stages of the archived teacher studies (benchmarks/archive/study_teacher_inputs.py):
#: more stage lights, a key pose every 3rd frame, every frame
STAGES = {"shading_l128": {"lights": 128}, "shading_k3": {"keyframe_every": 3},
          "shading_k1": {"keyframe_every": 1}}


def test_a_stage_is_another_capture_made_once(tmp_path, monkeypatch):
    """_common.study_capture: a stage that overrides some of the scale's settings trains
    on a capture of its own key (the scale's settings with that override), made once;
    the same settings find the capture already made."""
    made = []

    def fake(folder, *a):
        made.append((folder, a[2]))
        folder.mkdir(parents=True)
        (folder / "capture.json").write_text("{}")
    monkeypatch.setattr(B, "synth_capture", fake)
    plain, envs = B.study_capture(tmp_path, lambda m: None)
    dense, _ = B.study_capture(tmp_path, lambda m: None, stage=STAGES["shading_l128"])
    assert plain != dense and [m[1]["lights"] for m in made] == [32, 128]
    assert {k: v for k, v in made[1][1].items() if k != "lights"} == \
        {k: v for k, v in made[0][1].items() if k != "lights"}
    assert B.study_capture(tmp_path, lambda m: None)[0] == plain and len(made) == 2
    assert plain.parent == tmp_path and plain.name.startswith("capture-")
    assert set(envs) == {"source", "train", "eval"} and envs["eval"]


def test_every_capture_setting_of_a_scale_or_stage_reaches_the_stage(monkeypatch):
    """_common.synth_capture hands the stage every setting a scale or a study's stage
    names (a stage's ``keyframe_every`` was once dropped, so a "more poses" capture was the
    converged one again under another key), and each of those names is one the stage
    knows: an unknown one is an error, never a silent default."""
    import dataclasses
    import inspect
    import json

    from relight_cli.jobs import synth_capture as J
    from relight_cli.render.capture import StageSettings
    known = ({f.name for f in dataclasses.fields(StageSettings)}
             | set(inspect.signature(J.make_capture).parameters))
    seen = []
    monkeypatch.setattr(J, "make_capture", lambda folder, hand, **kw: seen.append(kw))
    scales = json.loads(B.SCALES.read_text())
    for stage in STAGES.values():
        capture = {**scales["converged"]["capture"], **stage}
        B.synth_capture("x", "builtin:right", 0, capture, [])
        assert all(seen[-1][k] == v for k, v in capture.items())
        assert seen[-1]["eval_env_space"] == capture.get("eval_env_space", "vertices")
    assert seen[-1]["keyframe_every"] == 1 != seen[0].get("keyframe_every", 10)
    for name, scale in scales.items():
        if isinstance(scale, dict) and "capture" in scale:
            assert set(scale["capture"]) <= known, name
    with __import__("pytest").raises(TypeError):
        StageSettings(**{"keyframes": 3})


def _imports(path: Path) -> set:
    """Top-level module names ``path`` imports (anywhere in it, lazily too)."""
    import ast
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
    return names


def test_scripts_share_only_common_and_never_import_the_cli():
    """benchmarks/ outside archive/: a script imports ``_common`` and the library, never
    another script's helpers (so no import circle) and never ``commands`` (the CLI);
    ``bench_presets`` and ``study_hands`` share their captures through ``_common``."""
    scripts = {p.stem: p for p in BENCH.glob("*.py")}
    assert "study_hands" in scripts and not [s for s in scripts
                                             if s.startswith("study_") and s != "study_hands"]
    for name, path in scripts.items():
        imported = _imports(path)
        assert not {m for m in imported if m.split(".")[0] in scripts} - {"_common"}, name
        assert not [m for m in imported if m == "commands" or m.startswith("commands.")
                    or m.startswith("relight_cli.commands")], name
    assert "_common" not in {m.split(".")[0] for m in _imports(scripts["_common"])} - {"_common"}


def _preset_record(model: str, last: float, gap: float, ceiling: float = 33.0) -> dict:
    """A ``--metrics-out`` record as train-teacher (a teacher) or distill (a student)
    writes it: the validation curve and the final scores with their ceiling."""
    def split(psnr):
        return {"psnr": psnr, "ceiling": {"psnr": ceiling}, "gap_to_ceiling": ceiling - psnr,
                "samples": 8}
    key = "heldout" if model in ("olat", "ggx", "linear") else "vs_ground_truth"
    history = [{"step": s, key: {"psnr": v}} for s, v in ((1000, 20.0), (4000, last - 0.1),
                                                          (5000, last))]
    final = {key: split(ceiling - gap)}
    if key == "heldout":
        final["heldout_all"] = split(ceiling - gap)
        final["heldout"] = split(ceiling - gap - 2.0)     # the 16 validation samples
        final["env"] = split(ceiling - 1.5)
    else:
        final["vs_teacher"] = {"psnr": 30.0}
    return {"wall_s": 600.0, "metrics": {"metrics": final, "details": {"history": history}}}


def test_presets_judge_a_teacher_on_every_held_out_sample_and_a_student_on_env_maps(tmp_path):
    """bench_presets: a teacher's goal is read on every held-out LED sample (not the 16 of
    its curve), a student's under env maps against the ground truth, where the table
    splits off its teacher's own env error; the students' commands distil the olat
    teacher the run trains, which is always among the commands."""
    import bench_presets as P
    rows = [P._row("olat", _preset_record("olat", 30.0, 0.9)),
            P._row("student", _preset_record("student", 29.0, 3.0))]
    assert rows[0]["goal"]["gap"] == pytest.approx(0.9) and rows[0]["converged"]
    assert rows[1]["goal_split"] == "env" and rows[1]["vs_teacher_psnr"] == 30.0
    machine = {"platform": "p", "cpus": 2, "load_average": "0", "gemm_gflops": 1.0,
               "memory_gbs": 1.0}
    md = P._markdown({"command": "x", "machine": machine, "threads": 1, "workers": 2,
                      "preset": "cpu", "quick": False, "wall_s": 60.0, "rows": rows})
    assert "| olat | 5000 | 10.0 | 32.10 | 33.00 | +0.90 | 31.50 | 33.00 | +1.50 | — |" in md
    assert "| student | 5000 | 10.0 | — | — | — | 30.00 | 33.00 | +3.00 | 30.00 |" in md
    assert "3.00 dB below the ceiling, 1.50 of it the teacher's, 1.50 its own" in md
    assert "| yes |" in md and "| no (env) |" in md
    envs = {"train": ["a.hdr"], "eval": ["b.hdr"]}
    cmds = P._commands(["dram", "linear"], tmp_path, tmp_path / "cap", envs, "cpu")
    assert list(cmds) == ["olat", "dram", "linear"]
    assert cmds["dram"][:2] == ["distill", tmp_path / "olat.pt"]
    assert cmds["olat"][-2] == tmp_path / "olat.json" and "--model" in cmds["olat"]


@pytest.mark.parametrize("argv", [["--workers", "0"], ["--threads", "0"], ["--models", ","],
                                  ["--models", "olat,teacher"]])
def test_presets_bad_options_are_usage_errors_before_anything_is_written(tmp_path, capsys,
                                                                         argv):
    """bench_presets: a worker or thread count below 1, no model or an unknown one is exit
    2 with one line, before the output or work folder is made or a model trained."""
    import bench_presets as P
    out, work = tmp_path / "out", tmp_path / "work"
    with pytest.raises(SystemExit) as e:
        P.main([*argv, "--out", str(out), "--work", str(work)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    named = argv[0] if argv[0] != "--models" else "model"
    assert ": error: " in err[-1] and named in err[-1]
    assert not out.exists() and not work.exists()


@pytest.mark.parametrize("script", sorted(p.name for p in BENCH.glob("*.py")
                                          if p.name != "_common.py"))
def test_every_script_answers_help(script):
    """Each script in the product path (benchmarks/, not archive/) runs: ``--help`` is
    usage and exit 0 (its imports resolve, nothing is made)."""
    r = subprocess.run([sys.executable, str(BENCH / script), "--help"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"usage: {script}"), r.stdout[:200]


def test_parser_errors_are_one_line_and_types_bound_values(capsys):
    """_common.ArgumentParser: argparse's errors as ``<prog>: error: …``, exit 2, no usage
    block; integer / number / integers refuse what is not a count, size or list."""
    ap = B.ArgumentParser(prog="bench_x.py")
    ap.add_argument("--n", type=B.integer(1))
    ap.add_argument("--t", type=B.number(0))
    ap.add_argument("--res", type=B.integers(1, "x", 2))
    assert vars(ap.parse_args(["--n", "3", "--t", "0.5", "--res", "8x16"])) == \
        {"n": 3, "t": 0.5, "res": "8x16"}
    for argv, word in ((["--n", "0"], "--n"), (["--n", "1.5"], "--n"), (["--t", "inf"], "--t"),
                       (["--t", "-1"], "--t"), (["--res", "8x"], "--res"),
                       (["--res", "8x16x2"], "--res"), (["--what"], "--what"), (["--n"], "--n")):
        with pytest.raises(SystemExit) as e:
            ap.parse_args(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("bench_x.py: error: "), err
        assert word in err and "usage" not in err
    with pytest.raises(SystemExit) as e:
        ap.error("a message\nover two lines")
    assert e.value.code == 2
    assert capsys.readouterr().err == "bench_x.py: error: a message over two lines\n"
    assert isinstance(B.parser("doc"), B.ArgumentParser)
