"""benchmarks/_common.py: the missing-matplotlib line, the shared options, the plot helper;
study_student_env.py's verdicts."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
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


def _env_row(psnr: float, tail: float = 0.05) -> dict:
    import study_student_env as E
    row = {s: {"psnr": psnr, "mse": 10 ** (-psnr / 10)} for s in E.SPLITS}
    for truth in E.TRUTHS:
        row[truth].update(gap=34.0 - psnr, ceiling=34.0, ceiling_mse=10 ** -3.4)
    return {**row, "gain_tail_db": tail, "wall_s": 600.0}


def test_student_env_verdicts_pair_each_variant_with_its_base():
    """study_student_env: a student variant is judged against ``tied`` and DRAM with
    synthesized env maps against DRAM, paired by seed, by max(2σ, 0.2 dB)."""
    import study_student_env as E
    runs = {"tied": [_env_row(24.0), _env_row(24.5)],
            "mix": [_env_row(25.0), _env_row(25.6)],          # +1.05 ± 0.07 dB: better
            "untied": [_env_row(24.1), _env_row(24.6)],       # +0.1 dB: a tie
            "dram": [_env_row(16.0, 0.5), _env_row(16.2)],
            "dram_mix": [_env_row(14.0), _env_row(17.2)]}     # −0.5 ± 2.1 dB: a tie
    res = E.summarize(runs)
    assert "versus" not in res["tied"] and "versus" not in res["dram"]
    assert res["mix"]["versus"]["base"] == "tied" and res["dram_mix"]["versus"]["base"] == "dram"
    for split in E.SPLITS:
        assert res["mix"]["versus"]["splits"][split]["verdict"] == "better"
        assert res["untied"]["versus"]["splits"][split]["verdict"] == "tie"
        d = res["dram_mix"]["versus"]["splits"][split]
        assert d["verdict"] == "tie" and abs(d["diff_db"] + 0.5) < 1e-9
        assert d["margin_db"] > 4
    assert not res["dram"]["converged"] and res["mix"]["converged"]
    assert abs(res["mix"]["ground_truth"]["gap"][0] - 8.7) < 1e-9


def test_student_env_reports_whether_drams_light_path_trained():
    """DRAM runs carry their light response; the summary gives its mean ± std over seeds
    and the table a row per DRAM variant with each seed's explained share; a variant
    without it (the texel-aligned student) has no such row."""
    import study_student_env as E

    def lit(row, explained):
        return {**row, "light": {"std": 0.1, "teacher_std": 0.2, "corr": 0.5,
                                 "explained": explained}}
    runs = {"dram": [lit(_env_row(16.0), 0.01), lit(_env_row(17.0), 0.35)],
            "dram_b8": [lit(_env_row(17.3), 0.39), lit(_env_row(17.4), 0.36)],
            "tied": [_env_row(24.0), _env_row(24.5)]}
    res = E.summarize(runs)
    assert abs(res["dram"]["light"]["explained"][0] - 0.18) < 1e-12
    assert abs(res["dram"]["light"]["explained"][1] - 0.34 / 2 ** 0.5) < 1e-12
    assert "light" not in res["tied"] and E.is_dram("dram_b8") and not E.is_dram("tied")
    for e in res.values():
        for r in e["seeds"]:
            r["curve"] = [[1000, 14.0]]
    record = {"command": "c", "machine": {"platform": "p", "cpus": 2, "load_average": "1",
                                          "gemm_gflops": 1.0, "memory_gbs": 1.0},
              "wall_s": 60.0, "seeds": [0, 1], "envs": {"train": ["builtin:sky"],
                                                        "eval": ["x.hdr"]},
              "variants": {v: E.VARIANTS[v] for v in runs}, "results": res}
    text = E._markdown(record)
    assert "| dram | 0.100 ± 0.000 (0.200) | 0.50 ± 0.00 | 0.18 ± 0.24 | 0.01, 0.35 |" in text
    assert "| dram_b8 |" in text and "| tied |" not in text


def test_student_env_judges_a_student_of_another_teacher_on_the_ground_truth_only(tmp_path):
    """A variant distilled from another teacher (``linear_tshading``) is compared with its
    base on the ground truth alone (against two different teachers nothing is shared); it
    caches that teacher's textures apart and passes no ``teacher`` field to ``distill``."""
    import study_student_env as E
    import study_teacher_inputs as T
    runs = {"linear": [_env_row(27.0), _env_row(27.4)],
            "linear_tshading": [_env_row(28.0), _env_row(28.5)]}
    versus = E.summarize(runs)["linear_tshading"]["versus"]
    assert versus["base"] == "linear" and list(versus["splits"]) == list(E.TRUTHS)
    assert versus["splits"]["ground_truth"]["verdict"] == "better"
    assert versus["splits"]["ground_truth_texels"]["verdict"] == "better"
    assert E.teacher_of("linear_tshading") == "shading" and E.teacher_of("linear") == "paper"
    assert "teacher" not in E.student_config("linear_tshading")
    assert E.textures_dir(tmp_path, "paper", 1) == tmp_path / "textures_s1"
    assert E.textures_dir(tmp_path, "shading", 1) == tmp_path / "textures_shading_s1"
    # a teacher of another stage: its study variant, judged against the student of the
    # 32-light teacher on the ground truth alone
    assert E.teacher_of("linear_tl128") == "shading_l128" and E.BASES["linear_tl128"] == \
        "linear_tshading" and "shading_l128" in T.STAGES


def test_student_env_convergence_reads_the_last_interval_when_validation_is_sparse():
    """Validated every 1,000 of 4,000 iterations, no point lies in the last 20 %: the gain
    is read over the last interval (3,000 → 4,000), never left unknown; a curve with a
    point inside the tail still uses the tail."""
    import study_student_env as E

    def record(points):
        history = [{"step": s, "vs_teacher": {"psnr": v}} for s, v in points]
        return {"wall_s": 1.0, "metrics": {"metrics": {
            "vs_ground_truth": {"mse": 1e-2, "psnr": 20.0, "ssim": 0.9, "samples": 4,
                                "ceiling": {"psnr": 30.0, "mse": 1e-3},
                                "gap_to_ceiling": 10.0},
            "vs_teacher": {"psnr": points[-1][1]}}, "details": {"history": history}}}

    sparse = E._seed_row(record([(1000, 20.0), (2000, 22.0), (3000, 23.0), (4000, 23.5)]), {}, {})
    assert sparse["tail_from"] == 3000 and abs(sparse["gain_tail_db"] - 0.5) < 1e-12
    dense = E._seed_row(record([(3000, 23.0), (3500, 23.4), (4000, 23.5)]), {}, {})
    assert dense["tail_from"] == 3500 and abs(dense["gain_tail_db"] - 0.1) < 1e-12


def _teacher_row(psnr: float) -> dict:
    split = {"psnr": psnr, "gap": 32.0 - psnr, "ceiling": 32.0, "ssim": 0.9}
    return {"wall_s": 600.0, "gain_tail_db": 0.1, "curve": [[0, 20.0], [10, psnr]],
            **{s: dict(split) for s in ("all_heldout", "all_train", "heldout", "fully_lit",
                                        "env", "env_texels")}}


def test_teacher_inputs_judges_against_the_named_base_and_a_stage_is_another_capture(
        tmp_path, monkeypatch):
    """study_teacher_inputs: ``--base`` names the variant the others are paired with (the
    paper's input stays out of it), and a variant on another stage trains on a capture of
    its own key (the scale's settings with that override), which the study makes once."""
    import bench_presets as P
    import study_hands as S
    import study_teacher_inputs as T
    runs = {"paper": [_teacher_row(20.0), _teacher_row(20.1)],
            "shading": [_teacher_row(30.0), _teacher_row(30.2)],
            "shading_l128": [_teacher_row(31.0), _teacher_row(31.3)]}    # +1.05 ± 0.07
    res = T.summarize(runs, [0, 1], base="shading")
    assert "versus_paper" not in res["shading"]
    assert res["paper"]["versus_paper"]["env"]["verdict"] == "worse"
    d = res["shading_l128"]["versus_paper"]["env"]
    assert d["verdict"] == "better" and abs(d["diff_db"] - 1.05) < 1e-9
    # another stage's frames are other images: judged on the gap to its own ceiling
    assert d["on"] == "gap" and res["paper"]["versus_paper"]["env"]["on"] == "psnr"
    runs["shading_l128"][0]["all_heldout"].update(psnr=40.0, gap=5.0)   # higher, but farther
    # the consistent env truth is the same images for every stage: judged on the PSNR
    runs["shading_l128"][0]["env_texels"].update(psnr=40.0, gap=5.0)
    worse = T.summarize(runs, [0, 1], base="shading")["shading_l128"]["versus_paper"]
    assert worse["all_heldout"]["diff_db"] < 0
    assert worse["env_texels"]["on"] == "psnr" and worse["env_texels"]["diff_db"] > 4
    del runs["paper"][1]["env_texels"]                  # a run scored before the column
    assert "env_texels" in T.summarize(runs, [0, 1], base="shading")["paper"]
    made = []
    monkeypatch.setattr(S, "synth_capture", lambda folder, *a: made.append((folder, a[2])))
    plain, _ = P._capture(tmp_path, lambda m: None)
    dense, _ = P._capture(tmp_path, lambda m: None, stage=T.STAGES["shading_l128"])
    assert plain != dense and [m[1]["lights"] for m in made] == [32, 128]
    assert {k: v for k, v in made[1][1].items() if k != "lights"} == \
        {k: v for k, v in made[0][1].items() if k != "lights"}


def test_every_capture_setting_of_a_scale_or_stage_reaches_the_stage(monkeypatch):
    """study_hands.synth_capture hands the stage every setting a scale or a study's stage
    names (a stage's ``keyframe_every`` was once dropped, so a "more poses" capture was the
    converged one again under another key), and each of those names is one the stage
    knows: an unknown one is an error, never a silent default."""
    import dataclasses
    import inspect
    import json

    import study_hands as S
    import study_teacher_inputs as T
    from relight_cli.jobs import synth_capture as J
    from relight_cli.render.capture import StageSettings
    known = ({f.name for f in dataclasses.fields(StageSettings)}
             | set(inspect.signature(J.make_capture).parameters))
    seen = []
    monkeypatch.setattr(J, "make_capture", lambda folder, hand, **kw: seen.append(kw))
    scales = json.loads((S.HERE / "studies" / "scales.json").read_text())
    for stage in T.STAGES.values():
        capture = {**scales["converged"]["capture"], **stage}
        S.synth_capture("x", "builtin:right", 0, capture, [])
        assert all(seen[-1][k] == v for k, v in capture.items())
        assert seen[-1]["eval_env_space"] == capture.get("eval_env_space", "vertices")
    assert seen[-1]["keyframe_every"] == 1 != seen[0].get("keyframe_every", 10)
    for name, scale in scales.items():
        if isinstance(scale, dict) and "capture" in scale:
            assert set(scale["capture"]) <= known, name
    with __import__("pytest").raises(TypeError):
        StageSettings(**{"keyframes": 3})


def test_eval_poses_below_one_is_a_usage_error_before_anything_is_written(tmp_path, capsys):
    """``--eval-poses 0`` (study_teacher_inputs, study_teacher_directions): exit 2 with one
    line naming the option, and no output folder made."""
    import study_teacher_directions as D
    import study_teacher_inputs as T
    for main, extra in ((T.main, ["--variants", "shading", "--base", "shading"]),
                        (D.main, [])):
        out = tmp_path / "out"
        with pytest.raises(SystemExit) as e:
            main(["--eval-poses", "0", "--out", str(out), "--work", str(tmp_path / "w"),
                  *extra])
        assert e.value.code == 2 and "--eval-poses" in capsys.readouterr().err
        assert not out.exists() and not (tmp_path / "w").exists()


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
