"""The README's numbers from the converged study are the committed tables' numbers: each
figure quoted in README "Do the papers' claims hold?" (or in benchmarks/README.md's
expansion of it, table by table) is read back from benchmarks/results/converged/*.json,
and its two summary tables are benchmarks/readme_tables.py's output (a rerun that moves a
number fails here until the README says what the table says)."""

from __future__ import annotations

import json
import re

import pytest

from conftest import ROOT

RESULTS = ROOT / "benchmarks" / "results" / "converged"


def _docs() -> str:
    """README.md and benchmarks/README.md, where the README's summary of the converged
    tables is expanded table by table (the sections below are read from either)."""
    return "\n".join((ROOT / f).read_text(encoding="utf-8")
                     for f in ("README.md", "benchmarks/README.md"))


def _readme_section() -> str:
    text = _docs()
    return text.split("**URHand Table 2, converged**", 1)[1].split(
        "**URHand Table 3, converged**", 1)[0]


def _readme_t3() -> str:
    text = _docs()
    return text.split("**URHand Table 3, converged**", 1)[1].split(
        "**RelightableHands Table 1/3, converged**", 1)[0]


def _readme_rh_t13() -> str:
    text = _docs()
    return text.split("**RelightableHands Table 1/3, converged**", 1)[1].split(
        "**RelightableHands Table 2, converged**", 1)[0]


def _listed(words) -> str:
    """``a and b``, ``a, b and c``: how the README lists per-seed numbers."""
    words = list(words)
    return " and ".join([", ".join(words[:-1]), words[-1]] if len(words) > 1 else words)


def _readme_rh_t2() -> str:
    text = _docs()
    return text.split("**RelightableHands Table 2, converged**", 1)[1].split(
        "`make test` runs the orderings", 1)[0]


@pytest.mark.skipif(not (RESULTS / "study_ur_t2.json").exists(), reason="no converged table")
def test_readme_quotes_the_converged_urhand_table():
    rec = json.loads((RESULTS / "study_ur_t2.json").read_text())
    ours = rec["rows"]["Ours (linear)"]["right"]
    text = _readme_section()
    quoted = [float(x) for x in re.findall(r"\d+\.\d+", text)]

    def shown(value, digits=2):
        return round(value, digits) in quoted

    for split in ("heldout", "fully_lit", "env"):
        assert shown(ours[split]["psnr"]["mean"]), (split, ours[split]["psnr"]["mean"], quoted)
        assert shown(ours[split]["ceiling"]["psnr"]["mean"]), split
    assert shown(ours["heldout"]["psnr"]["std"]) and shown(ours["fully_lit"]["psnr"]["std"])
    verdicts = [h["verdict"] for c in rec["claims"] for h in c["hands"].values()]
    assert "all five of the paper's claims reproduced" in text
    assert verdicts == ["reproduced"] * 5
    assert f"{rec['row_seconds'] / 3600:.1f} h of row training" in text


@pytest.mark.skipif(not (RESULTS / "study_ur_t3.json").exists(), reason="no converged table")
def test_readme_quotes_the_converged_urhand_feature_table():
    rec = json.loads((RESULTS / "study_ur_t3.json").read_text())
    text = _readme_t3()
    quoted = [float(x) for x in re.findall(r"\d+\.\d+", text)]
    for row in ("Full model", "Phong", "w/o specular", "w/o visibility", "w/o refiner"):
        held = rec["rows"][row]["right"]["heldout"]["psnr"]
        assert round(held["mean"], 2) in quoted, (row, held["mean"], quoted)
    full = rec["rows"]["Full model"]["right"]["heldout"]
    assert round(full["ceiling"]["psnr"]["mean"], 2) in quoted
    for value in rec["rows"]["w/o refiner"]["right"]["heldout"]["psnr"]["values"]:
        assert round(value, 2) in quoted
    verdicts = [h["verdict"] for c in rec["claims"] for h in c["hands"].values()]
    assert verdicts[:3] == ["reproduced"] * 3 and verdicts[3].startswith("tie")
    assert "three of the paper's four claims reproduced" in text and "w/o refiner is a tie" in text
    assert f"{rec['row_seconds'] / 3600:.1f} h of row training" in text


@pytest.mark.skipif(not (RESULTS / "study_rh_t13.json").exists(), reason="no converged table")
def test_readme_quotes_the_converged_teacher_table():
    rec = json.loads((RESULTS / "study_rh_t13.json").read_text())
    text = _readme_rh_t13()
    quoted = [float(x) for x in re.findall(r"\d+\.\d+", text)]
    rows = rec["rows"]
    for row in ("Ours (teacher)", "w/o visibility", "GGX [6, 61]"):
        for hand in ("right", "left", "both"):
            mse = rows[row][hand]["heldout"]["mse"]["mean"] * 1e3
            assert round(mse, 3) in quoted, (row, hand, mse, quoted)
    teacher = [rows["Ours (teacher)"][h]["heldout"]["gap_to_ceiling"]["mean"]
               for h in ("right", "left", "both")]
    ggx = [rows["GGX [6, 61]"][h]["heldout"]["gap_to_ceiling"]["mean"]
           for h in ("right", "left", "both")]
    assert f"teacher stays {min(teacher):.1f}–{max(teacher):.1f} dB below it" in text
    assert max(ggx) <= 0.7 and "within 0.7\ndB of its ceiling" in text
    verdicts = {(c["worse"], c["metric"], hand): h["verdict"] for c in rec["claims"]
                for hand, h in c["hands"].items()}
    assert len(verdicts) == 12
    for (worse, _, _), verdict in verdicts.items():
        assert verdict == ("reproduced" if worse == "w/o visibility"
                           else "not reproduced (reversed)"), (worse, verdict)
    assert "reproduced on all three" in text and "Table 3 reversed" in text
    assert f"{rec['row_seconds'] / 3600:.1f} h of row\ntraining" in text


@pytest.mark.skipif(not (RESULTS / "study_rh_t2.json").exists()
                    or not (RESULTS / "student_gap.json").exists(), reason="no converged table")
def test_readme_quotes_the_converged_student_table():
    rec = json.loads((RESULTS / "study_rh_t2.json").read_text())
    gap = json.loads((RESULTS / "student_gap.json").read_text())
    text = _readme_rh_t2()
    quoted = [float(x) for x in re.findall(r"\d+\.\d+", text)]
    rows = rec["rows"]
    for row in ("Ours (student)", "w/o specular", "w/o visibility", "DRAM [4]"):
        for split in ("vs_teacher", "vs_ground_truth"):
            mse = rows[row]["right"][split]["mse"]["mean"] * 1e3
            assert round(mse, 3) in quoted, (row, split, mse, quoted)
    ours = rows["Ours (student)"]["right"]["vs_ground_truth"]
    assert round(ours["ceiling"]["mse"]["mean"] * 1e3, 3) in quoted
    assert f"{ours['gap_to_ceiling']['mean']:.2f} dB below its ceiling" in text
    verdicts = {(c["worse"], c["metric"].split(".")[0]): h["verdict"]
                for c in rec["claims"] for h in c["hands"].values()}
    assert len(verdicts) == 6
    for (worse, split), verdict in verdicts.items():
        tie = worse == "w/o specular" and split == "vs_teacher"
        assert verdict.startswith("tie") if tie else verdict == "reproduced", (worse, split)
    assert "both reproduced against the teacher and against the ground truth" in text
    assert "a tie against the teacher and help against the ground truth" in text
    # the split of the student's gap, read back from student_gap.json
    parts = {k: sum(s["split_db"][k] for s in gap["seeds"]) / len(gap["seeds"])
             for k in ("teacher", "env_grid", "distillation", "total")}
    assert abs(parts["total"] - ours["gap_to_ceiling"]["mean"]) < 0.01
    assert f"{parts['teacher']:.1f} dB is the teacher's own error" in text
    assert f"{parts['env_grid']:.1f} dB the 8×16 env grid" in text
    assert f"{parts['distillation']:.1f} dB is distillation" in text
    assert f"{rec['row_seconds'] / 3600:.1f} h of row\ntraining" in text


@pytest.mark.skipif(not (RESULTS / "teacher_inputs.json").exists(), reason="no study table")
def test_readme_quotes_the_teacher_inputs_study():
    """The teacher's gap on every sample (and the half vector's gain) as the README's Table
    1/3 and presets paragraphs quote them, read back from teacher_inputs.json."""
    rec = json.loads((RESULTS / "teacher_inputs.json").read_text())["results"]
    text = _docs()
    t13 = _readme_rh_t13()
    paper, half = rec["paper"], rec["half"]
    held, train = paper["all_heldout"]["gap"][0], paper["all_train"]["gap"][0]
    assert f"is {train:.2f} dB below its ceiling on its 384 training images" in t13
    assert f"but {held:.2f} dB\nbelow it on the 128 held-out ones" in t13
    assert f"(the 16 read {paper['heldout']['gap'][0]:.2f}:" in t13
    gain = half["versus_paper"]["all_heldout"]
    assert gain["verdict"] == "better" and f"gains\n{gain['diff_db']:.2f} dB there" in t13
    assert all(r["all_heldout"]["psnr"] > p["all_heldout"]["psnr"]
               for r, p in zip(half["seeds"], paper["seeds"])) and "on every seed" in t13
    assert half["versus_paper"]["env"]["verdict"] == "tie" and "ties under env maps" in t13
    assert all(r["all_heldout"]["samples"] == 128 and r["all_train"]["samples"] == 384
               for r in paper["seeds"] + half["seeds"])
    assert (f"on every sample {held:.2f} dB short on new poses and {train:.2f} dB on its "
            f"training poses") in text.replace("\n", " ")


@pytest.mark.skipif(not (RESULTS / "teacher_shading" / "teacher_inputs.json").exists(),
                    reason="no study table")
def test_readme_quotes_the_shading_input_study():
    """The shading input's gain, verdicts and gaps as the README quotes them, read back
    from teacher_shading/teacher_inputs.json; the cpu preset uses it because it is better
    on held-out poses and fully lit frames and never worse."""
    rec = json.loads((RESULTS / "teacher_shading" / "teacher_inputs.json").read_text())
    res = rec["results"]
    t13 = " ".join(_readme_rh_t13().split())
    text = " ".join(_docs().split())
    paper, ours = res["paper"], res["shading"]
    vs = ours["versus_paper"]
    held, lit = vs["all_heldout"], vs["fully_lit"]
    assert held["verdict"] == lit["verdict"] == "better"
    assert all(d["verdict"] != "worse" for d in vs.values())
    assert f"gains +{held['diff_db']:.2f} ± {held['std_db']:.2f} dB on every held-out" in t13
    assert (f"({ours['all_heldout']['psnr'][0]:.2f} against "
            f"{paper['all_heldout']['psnr'][0]:.2f} dB, gap to the ceiling "
            f"{paper['all_heldout']['gap'][0]:.2f} to {ours['all_heldout']['gap'][0]:.2f} dB)"
            ) in t13
    assert f"+{lit['diff_db']:.2f} ± {lit['std_db']:.2f} dB under the fully lit" in t13
    assert f"fits the training poses to {ours['all_train']['gap'][0]:.2f} dB" in t13
    assert vs["env"]["verdict"] == "tie" and "ties under the held-out env maps" in t13
    assert len(rec["seeds"]) == 3 and "three seeds" in t13
    nopose = res["nopose"]["versus_paper"]
    assert all(d["verdict"] == "tie" for d in nopose.values())
    d = nopose["all_heldout"]
    assert f"({d['diff_db']:.2f} ± {d['std_db']:.2f} dB)".replace("-", "−") in t13
    assert (f"{ours['all_heldout']['gap'][0]:.2f} dB short on new poses, "
            f"{ours['all_train']['gap'][0]:.2f} dB on its training poses") in text
    student = json.loads((RESULTS / "student_tshading" / "student_env.json").read_text())
    d = student["results"]["linear_tshading"]["versus"]["splits"]["ground_truth"]
    gt = student["results"]["linear_tshading"]["ground_truth"]["psnr"]
    assert d["verdict"] == "tie" and list(student["variants"]) == ["linear", "linear_tshading"]
    assert (f"three seeds: {gt[0]:.2f} ± {gt[1]:.2f} dB against the ground truth, a tie, "
            f"{d['diff_db']:+.2f} ± {d['std_db']:.2f} dB)") in t13
    from relight_cli.neural.config import resolve_config
    assert resolve_config("cpu").inputs == "shading"


@pytest.mark.skipif(not (RESULTS / "env_truth" / "env_truth.json").exists(),
                    reason="no study table")
def test_readme_quotes_the_env_truth_and_led_density_studies():
    """The env-map ground truth's share of the gap and the 128-LED stage, as the README
    quotes them, read back from env_truth.json and teacher_lights/teacher_inputs.json;
    the stage's superposition error is what the default ``texels`` makes small."""
    rec = json.loads((RESULTS / "env_truth" / "env_truth.json").read_text())
    res, sup = rec["results"], rec["superposition"]
    t13 = " ".join(_readme_rh_t13().split())
    text = " ".join(_docs().split())
    assert (f"up to {100 * sup['vertices']['max']:.0f} % (relative MSE; median "
            f"{100 * sup['vertices']['median']:.2f} %)") in t13
    assert sup["texels"]["max"] < 1e-3 and \
        f"{100 * sup['texels']['max']:.2f} % at most" in t13
    for name, label in (("paper", "paper input"), ("shading", "shading input")):
        v, t = res[name]["vertices"]["gap"], res[name]["texels"]["gap"]
        assert res[name]["gap_change"]["verdict"] == "smaller"
        assert (f"{v[0]:.2f} to {t[0]:.2f} ± {t[1]:.2f} dB ({label})") in t13
    st = res["student linear"]
    assert (f"from {st['vertices']['gap'][0]:.2f} to {st['texels']['gap'][0]:.2f} ± "
            f"{st['texels']['gap'][1]:.2f} dB") in t13
    assert f"{st['texels']['gap'][0]:.2f} dB short" in text
    for name, label in (("linear", "URHand's linear model's"), ("ggx", "GGX baseline's")):
        v, t = res[name]["vertices"]["gap"][0], res[name]["texels"]["gap"][0]
        assert f"{label} (one seed) from {v:.2f} to {t:.2f} dB" in t13
    assert rec["model_seeds"] == [0]
    ceil = {sp: res["paper"][sp]["ceiling"] for sp in ("vertices", "texels")}
    assert f"from {ceil['vertices']:.2f} to {ceil['texels']:.2f} dB" in t13
    gains = [e["texels"]["psnr"][0] - e["vertices"]["psnr"][0] for e in res.values()]
    assert min(gains) > -0.05 and max(gains) < 0.55 and "gain 0.0–0.5 dB" in t13
    lights = json.loads((RESULTS / "teacher_lights" / "teacher_inputs.json").read_text())
    dense = lights["results"]["shading_l128"]
    held, env = dense["versus_paper"]["all_heldout"], dense["versus_paper"]["env"]
    assert lights["base"] == "shading" and held["on"] == "gap" and held["verdict"] == "better"
    assert env["verdict"] == "tie"
    assert (f"from {lights['results']['shading']['all_heldout']['gap'][0]:.2f} to "
            f"{dense['all_heldout']['gap'][0]:.2f} ± {dense['all_heldout']['gap'][1]:.2f} dB "
            f"(+{held['diff_db']:.2f} ± {held['std_db']:.2f} dB, better)") in t13
    assert f"tie under env maps (+{env['diff_db']:.2f} ± {env['std_db']:.2f} dB)" in t13


def test_readme_quotes_the_consistent_truth_of_the_student_tables():
    """The student tables' second ground-truth column (eval_env_space texels), as the
    README quotes it, read back from student_linear/student_env.json."""
    rec = json.loads((RESULTS / "student_linear" / "student_env.json").read_text())
    res = rec["results"]
    lin, tied = res["linear"]["ground_truth_texels"], res["tied"]["ground_truth_texels"]
    d = res["linear"]["versus"]["splits"]["ground_truth_texels"]
    text = " ".join(_docs().split())
    assert d["verdict"] == "better"
    assert (f"the linear head reaches {lin['psnr'][0]:.2f} ± {lin['psnr'][1]:.2f} dB against "
            f"the paper head's {tied['psnr'][0]:.2f} ± {tied['psnr'][1]:.2f} "
            f"(+{d['diff_db']:.2f} ± {d['std_db']:.2f} dB, better; gaps "
            f"{lin['gap'][0]:.2f} and {tied['gap'][0]:.2f} dB)") in text
    # the same scores as the grid study's training-grid column (one scorer; the grid study
    # ran before checkpoints loaded in their training layout: float rounding apart)
    grid = json.loads((RESULTS / "student_grid" / "student_grid.json").read_text())
    assert grid["results"]["linear"]["grids"]["8x16"]["psnr"] == pytest.approx(lin["psnr"],
                                                                                abs=1e-4)


def test_readme_quotes_the_dram_rerun():
    """DRAM at ``cpu`` with both truths, as the README quotes it (student_dram)."""
    rec = json.loads((RESULTS / "student_dram" / "student_env.json").read_text())
    res = rec["results"]
    d, tx = res["dram"], res["dram"]["ground_truth_texels"]
    mix = res["dram_mix"]["versus"]["splits"]["ground_truth_texels"]
    text = " ".join(_docs().split())
    assert rec["seeds"] == [0, 1] and mix["verdict"] == "tie"
    assert (f"{tx['psnr'][0]:.2f} ± {tx['psnr'][1]:.2f} dB against the consistent env truth "
            f"(gap {tx['gap'][0]:.2f} dB)") in text
    assert f"(`mix`) tie ({mix['diff_db']:+.2f} ± {mix['std_db']:.2f} dB)" in text
    assert (f"{d['heldout_pose_train_env']['psnr'][0]:.2f} dB against the teacher on held-out "
            f"poses under them") in text
    assert f"{d['wall_min'] / len(d['seeds']):.0f} min per run" in text


def test_readme_quotes_the_student_grid_study():
    """The student rendered on a finer env grid than it trained on, as the README quotes
    it, read back from student_grid/student_grid.json; and the ``cpu`` preset renders on
    the grid the study measured."""
    from relight_cli.neural.config import STUDENT_PRESET_MODEL, STUDENT_PRESETS
    rec = json.loads((RESULTS / "student_grid" / "student_grid.json").read_text())
    lin = rec["results"]["linear"]
    text = " ".join(_docs().split())
    fine, coarse = lin["grids"]["16x32"], lin["grids"]["8x16"]
    assert fine["vs_train"]["verdict"] == "better"
    assert min(a - b for a, b in zip(fine["per_seed"], coarse["per_seed"])) > 0
    assert (f"the same students are {fine['gap'][0]:.2f} ± {fine['psnr'][1]:.2f} dB short "
            f"(+{fine['vs_train']['diff_db']:.2f} ± {fine['vs_train']['std_db']:.2f} dB, "
            f"better on every seed), at {rec['render_s']['linear']['16x32']:.2f} instead of "
            f"{rec['render_s']['linear']['8x16']:.2f} s per frame") in text
    d = lin["split_db"]
    assert (f"{d['teacher'][0]:.2f} ± {d['teacher'][1]:.2f} dB teacher, "
            f"{d['env_grid'][0]:.2f} ± {d['env_grid'][1]:.2f} dB grid and "
            f"{d['distillation'][0]:.2f} ± {d['distillation'][1]:.2f} dB distillation") in text
    assert (f"recovers {-d['render_grid'][0]:.2f} ± {d['render_grid'][1]:.2f} of the grid's "
            f"{d['env_grid'][0]:.2f} dB ({lin['best_grid'].replace('x', '×')}; 16×32 recovers "
            f"{fine['vs_train']['diff_db']:.2f}") in text
    assert rec["grids"][0] == "x".join(map(str, STUDENT_PRESETS["cpu"]["env_res"]))
    assert STUDENT_PRESET_MODEL["cpu", "student"]["render_env_res"] == (16, 32)


@pytest.mark.skipif(not (RESULTS / "student_env.json").exists(), reason="no study table")
def test_readme_quotes_the_student_env_study():
    """The README's student paragraph quotes student_env.json: each variant's ground-truth
    PSNR and gap, the per-seed differences, the paired difference and its verdict."""
    res = json.loads((RESULTS / "student_env.json").read_text())["results"]
    text = " ".join(_readme_rh_t2().split())
    tied, both = res["tied"], res["untied_mix"]
    gt = "ground_truth"
    assert (f"from {tied[gt]['psnr'][0]:.2f} to {both[gt]['psnr'][0]:.2f} dB against the "
            "ground truth") in text
    assert f"(gap {tied[gt]['gap'][0]:.2f} to {both[gt]['gap'][0]:.2f} dB)" in text
    diffs = [a[gt]["psnr"] - b[gt]["psnr"] for a, b in zip(both["seeds"], tied["seeds"])]
    count = {2: "both", 3: "all three"}[len(diffs)]
    assert all(d > 0 for d in diffs) and f"higher on {count} seeds" in text
    signed = [f"{d:+.2f}" for d in diffs]
    assert "(" + ", ".join(signed[:-1]) + " and " + signed[-1] + " dB)" in text
    versus = both["versus"]["splits"][gt]
    assert versus["verdict"] == "tie"
    assert f"{versus['diff_db']:+.2f} ± {versus['std_db']:.2f} dB is a tie" in text
    minutes = sum(e["wall_min"] for e in res.values())
    assert f"{minutes:.0f} min of student training" in text
    gains = [s["gain_tail_db"] for e in (tied, both) for s in e["seeds"]]
    gaining = sum(g >= 0.2 for g in gains)
    words = dict(enumerate(["no", "one", "two", "three", "four", "five", "six"]))
    assert not (tied["converged"] and both["converged"])
    assert (f"{words[gaining]} of the {words[len(gains)]} runs were still gaining "
            f"(up to {max(gains):+.2f} dB") in text
    assert f"{tied[gt]['mse'][0] * 1e3:.2f} against 43.366" in text


@pytest.mark.skipif(not (RESULTS / "student_iters" / "student_env.json").exists(),
                    reason="no study table")
def test_readme_quotes_the_student_iterations_study():
    """The README's sentence on the student trained twice as long quotes
    student_iters/student_env.json: time, convergence, PSNRs, per-seed gains, verdict."""
    res = json.loads((RESULTS / "student_iters" / "student_env.json").read_text())["results"]
    text = " ".join(_readme_rh_t2().split())
    tied, long = res["tied"], res["tied_8k"]
    gt = "ground_truth"
    assert f"8,000 iterations, {long['wall_min'] / len(long['seeds']):.1f} min per student" in text
    gains = [s["gain_tail_db"] for s in long["seeds"]]
    assert long["converged"] and "the student converges (last-interval gains " + _listed(
        f"{g:+.2f}" for g in gains) + " dB)" in text
    assert f"goes from {tied[gt]['psnr'][0]:.2f} to {long[gt]['psnr'][0]:.2f} dB" in text
    diffs = [a[gt]["psnr"] - b[gt]["psnr"] for a, b in zip(long["seeds"], tied["seeds"])]
    assert "(" + _listed(f"{d:+.2f}" for d in diffs) + " dB per seed)" in text
    versus = long["versus"]["splits"][gt]
    assert versus["verdict"] == "tie"
    assert f"{versus['diff_db']:+.2f} ± {versus['std_db']:.2f} dB is still a tie" in text


def test_committed_results_name_no_machine_folders():
    """Every committed table, record and note under benchmarks/results names paths relative
    to the repository (``../shared/…``), never this checkout's absolute folders."""
    parent = str(ROOT.resolve().parent).rstrip("/") + "/"
    if parent == "/":
        pytest.skip("the checkout sits at the file system's root")
    found = [str(p.relative_to(ROOT)) for p in (ROOT / "benchmarks" / "results").rglob("*")
             if p.suffix in (".json", ".md", ".txt", ".csv") and p.is_file()
             and parent in p.read_text(encoding="utf-8", errors="replace")]
    assert not found, found


@pytest.mark.skipif(not (RESULTS / "student_linear" / "student_env.json").exists(),
                    reason="no study table")
def test_readme_quotes_the_linear_head_study():
    """The README's paragraph on the student's linear head quotes
    student_linear/student_env.json (and the 8,000-iteration paper head it is set
    against): PSNRs and gaps, the paired difference, its verdict, per-seed differences,
    minutes per student, last-interval gains, and the closed-form rows; the presets
    section quotes the same row."""
    res = json.loads((RESULTS / "student_linear" / "student_env.json").read_text())["results"]
    long = json.loads((RESULTS / "student_iters" / "student_env.json").read_text())["results"]
    text = " ".join(_readme_rh_t2().split())
    whole = " ".join(_docs().split())
    gt = "ground_truth"
    tied, lin, lsq, start = res["tied"], res["linear"], res["lsq"], res["linear_lsq"]
    held, train = "heldout_pose_eval_env", "heldout_pose_train_env"
    assert (f"{tied[train]['psnr'][0]:.2f} dB against the teacher on held-out poses under "
            f"training maps and {tied[held]['psnr'][0]:.2f} under held-out maps") in text
    assert (f"scores {lsq[train]['psnr'][0]:.2f} and {lsq[held]['psnr'][0]:.2f} dB") in text
    assert lsq[train]["psnr"][0] > tied[train]["psnr"][0]
    assert lsq[held]["psnr"][0] > tied[held]["psnr"][0]
    assert (f"it reaches {lin[gt]['psnr'][0]:.2f} ± {lin[gt]['psnr'][1]:.2f} dB where the "
            f"paper's head has {tied[gt]['psnr'][0]:.2f} ± {tied[gt]['psnr'][1]:.2f}") in text
    assert f"(gap to the ceiling {tied[gt]['gap'][0]:.2f} to {lin[gt]['gap'][0]:.2f} dB)" in text
    versus = lin["versus"]["splits"][gt]
    assert versus["verdict"] == "better"
    assert f"{versus['diff_db']:+.2f} ± {versus['std_db']:.2f} dB, better by the 2σ" in text
    diffs = [a[gt]["psnr"] - b[gt]["psnr"] for a, b in zip(lin["seeds"], tied["seeds"])]
    assert all(d > 0 for d in diffs)
    assert "on every seed (" + _listed(f"{d:+.2f}" for d in diffs) + " dB)" in text
    for split in ("heldout_pose_eval_env", "train_pose_eval_env"):     # "under held-out maps"
        assert lin["versus"]["splits"][split]["verdict"] == "better", split
    per = {k: e["wall_min"] / len(e["seeds"]) for k, e in res.items()}
    assert f"in {per['linear']:.1f} instead of {per['tied']:.1f} min per student" in text
    gains = [s["gain_tail_db"] for s in lin["seeds"]]
    assert not lin["converged"]
    assert "still gaining at 4,000 iterations (" + _listed(f"{g:+.2f}" for g in gains) in text
    above = lin[gt]["psnr"][0] - long["tied_8k"][gt]["psnr"][0]
    assert f"already {above:.2f} dB above the paper's head trained for 8,000" in text
    assert lsq["converged"] and lsq["versus"]["splits"][gt]["verdict"] == "tie"
    assert (f"scores {lsq[gt]['psnr'][0]:.2f} ± {lsq[gt]['psnr'][1]:.2f} dB in "
            f"{per['lsq']:.1f} min, a tie with the paper's {per['tied']:.1f}-min student") in text
    assert start[gt]["psnr"][0] < lin[gt]["psnr"][0]
    assert f"below the grey start ({start[gt]['psnr'][0]:.2f} ± {start[gt]['psnr'][1]:.2f}" in text
    assert (f"{lin[gt]['psnr'][0]:.2f} dB, {lin[gt]['gap'][0]:.2f} dB short, in "
            f"{per['linear']:.0f} min") in whole


@pytest.mark.skipif(not (RESULTS / "student_linear_8k" / "student_env.json").exists(),
                    reason="no study table")
def test_readme_quotes_the_linear_head_at_8000_iterations():
    """The README's sentence on the linear head trained for 8,000 iterations quotes
    student_linear_8k/student_env.json and student_linear/student_env.json."""
    res = json.loads((RESULTS / "student_linear_8k" / "student_env.json").read_text())["results"]
    four = json.loads((RESULTS / "student_linear" / "student_env.json").read_text())["results"]
    text = " ".join(_readme_rh_t2().split())
    gt, held = "ground_truth", "heldout_pose_eval_env"
    long, short = res["linear_8k"], four["linear"]
    assert (f"({long[held]['psnr'][0]:.2f} against {short[held]['psnr'][0]:.2f} dB on held-out "
            "poses under held-out maps)") in text
    assert long[held]["psnr"][0] > short[held]["psnr"][0]
    assert f"ground truth ({long[gt]['psnr'][0]:.2f} ± {long[gt]['psnr'][1]:.2f} dB)" in text
    assert long[gt]["psnr"][0] <= short[gt]["psnr"][0] + 0.2          # "but not"
    assert all(d["verdict"] == "better" for d in long["versus"]["splits"].values())
    versus = long["versus"]["splits"][gt]
    assert f"({versus['diff_db']:+.2f} ± {versus['std_db']:.2f} dB against the ground" in text


def test_readme_quotes_the_dram_head_study():
    """DRAM with its head in texture units against Eq. 11's scale at ``cpu``, as the README
    quotes it (student_dram_head), and the Eq. 11 rows equal to the earlier DRAM table."""
    rec = json.loads((RESULTS / "student_dram_head" / "student_env.json").read_text())
    res = rec["results"]
    new, old = (res[v]["ground_truth_texels"]["psnr"] for v in ("dram", "dram_eq11"))
    versus = res["dram"]["versus"]["splits"]["ground_truth_texels"]
    text = " ".join(_docs().split())
    assert rec["seeds"] == [0, 1] and res["dram"]["versus"]["base"] == "dram_eq11"
    assert (f"{new[0]:.2f} ± {new[1]:.2f} against {old[0]:.2f} ± {old[1]:.2f} dB on the "
            f"consistent truth ({versus['diff_db']:+.2f} ± {versus['std_db']:.2f} dB, "
            f"{versus['verdict']})") in text
    before = json.loads((RESULTS / "student_dram" / "student_env.json").read_text())
    assert old == before["results"]["dram"]["ground_truth_texels"]["psnr"]


def test_readme_quotes_the_dram_batch_and_loss_study():
    """DRAM's light path at ``cpu`` per seed, and batches of 8 and the texture loss against
    the preset's DRAM, as the README quotes them (student_dram_b8, four seeds)."""
    rec = json.loads((RESULTS / "student_dram_b8" / "student_env.json").read_text())
    res = rec["results"]
    text = " ".join(_docs().split())
    assert rec["seeds"] == [0, 1, 2, 3]

    def shares(v):
        return [r["light"]["explained"] for r in res[v]["seeds"]]
    base = shares("dram")
    assert ("DRAM's texture explains " + ", ".join(f"{x:.2f}" for x in base[:-1])
            + f" and {base[-1]:.2f} of the teacher's variation") in text
    for v, span in (("dram_b8", "every seed ({}–{})"), ("dram_tex_b8", "them most ({}–{})")):
        lo, hi = min(shares(v)), max(shares(v))
        assert span.format(f"{lo:.2f}", f"{hi:.2f}") in text, v
        assert lo > max(base) or v == "dram_b8"           # "most": above every plain run
        assert lo > min(base) + 0.2                       # "on every seed": no dead run
    truth = "ground_truth_texels"
    b8, tex, plain = (res[v][truth]["psnr"] for v in ("dram_b8", "dram_tex_b8", "dram"))
    assert (f"{b8[0]:.2f} ± {b8[1]:.2f} and {tex[0]:.2f} ± {tex[1]:.2f} dB against DRAM's "
            f"{plain[0]:.2f} ± {plain[1]:.2f}") in text
    d = [res[v]["versus"]["splits"][truth] for v in ("dram_b8", "dram_tex_b8")]
    assert (f"({d[0]['diff_db']:+.2f} ± {d[0]['std_db']:.2f} and {d[1]['diff_db']:+.2f} ± "
            f"{d[1]['std_db']:.2f} dB, tie)") in text
    assert all(x["verdict"] == "tie" for x in d)
    # "does not generalize": the best-lit variant is no better under held-out maps
    assert tex[0] <= b8[0]
    mix = res["dram_tex_b8_mix"]["versus"]
    assert mix["base"] == "dram_tex_b8"
    d = [mix["splits"][k] for k in ("heldout_pose_eval_env", truth)]
    assert (f"under held-out maps ({d[0]['diff_db']:+.2f} ± {d[0]['std_db']:.2f} dB, "
            f"{d[0]['verdict']}) but not to the truth ({d[1]['diff_db']:+.2f} ± "
            f"{d[1]['std_db']:.2f} dB, {d[1]['verdict']})") in text
    assert d[0]["verdict"] == "better" and d[1]["verdict"] == "tie"


def _linear_student_study(variant: str):
    """(results, the README as one line, the variant's comparison) of the three-seed
    study of ``variant`` against the cpu preset's student (results/converged/student_V/)."""
    rec = json.loads((RESULTS / f"student_{variant}" / "student_env.json").read_text())
    assert rec["seeds"] == [0, 1, 2]
    versus = rec["results"][variant]["versus"]
    assert versus["base"] == "linear"
    text = " ".join(_docs().split())
    return rec["results"], text, versus


def test_readme_quotes_the_texture_loss_student_study():
    """The linear-head student on whole textures against the image loss, as the README
    quotes it (student_linear_tex, three seeds): worse by the 2σ rule, and falling."""
    res, text, versus = _linear_student_study("linear_tex")
    truth = "ground_truth_texels"
    tex, lin = res["linear_tex"][truth]["psnr"], res["linear"][truth]["psnr"]
    d = versus["splits"][truth]
    assert (f"{tex[0]:.2f} ± {tex[1]:.2f} against {lin[0]:.2f} ± {lin[1]:.2f} dB on the "
            f"consistent truth ({d['diff_db']:+.2f} ± {d['std_db']:.2f} dB, {d['verdict']})"
            ) in text
    assert d["verdict"] == "worse"
    # "it falls over its last 1,000 iterations on every seed"
    gains = [r["gain_tail_db"] for r in res["linear_tex"]["seeds"]]
    assert all(g < 0 for g in gains), gains


def test_readme_quotes_the_teacher_network_rate():
    """The cpu teacher's network and iteration against the same run's GEMM, one and two
    threads, as the README quotes them (bench_teacher.py --quick runs)."""
    text = " ".join(_docs().split())
    rows = {}
    for threads, path in ((1, RESULTS.parent / "teacher_t1" / "teacher.json"),
                          (2, RESULTS.parent / "teacher.json")):
        rec = json.loads(path.read_text())
        assert rec["machine"]["torch_threads"] == threads
        row = next(t for t in rec["throughput"] if t["preset"] == "cpu" and t["channels_last"])
        gemm = rec["machine"]["gemm_gflops"]
        rows[threads] = (row["network_alone"]["gflops"], 100 * row["network_alone"]["gflops"]
                         / gemm, 100 * row["gflops"] / gemm)
        assert row["network_alone"]["gflops"] <= rec["machine"]["peak_gflops"]
    net, net_pct, it_pct = rows[1]
    assert (f"runs at {net:.1f} GFLOP/s, {net_pct:.0f} % of the same run's GEMM, and a whole "
            f"training iteration at {it_pct:.0f} %") in text
    assert f"(two threads: {rows[2][1]:.0f} % and {rows[2][2]:.0f} %;" in text


def test_readme_quotes_the_synthesized_maps_student_study():
    """The linear-head student on synthesized env maps against the training maps alone,
    as the README quotes it (student_linear_mix, three seeds): a tie on every split."""
    res, text, versus = _linear_student_study("linear_mix")
    truth = "ground_truth_texels"
    mix, lin = res["linear_mix"][truth]["psnr"], res["linear"][truth]["psnr"]
    d = versus["splits"][truth]
    assert (f"{mix[0]:.2f} ± {mix[1]:.2f} against {lin[0]:.2f} ± {lin[1]:.2f} dB on the "
            f"consistent truth, {d['diff_db']:+.2f} ± {d['std_db']:.2f} dB, a tie on every "
            f"split") in text
    assert all(x["verdict"] == "tie" for x in versus["splits"].values())
    trained = res["linear"]["train_pose_eval_env"]["psnr"][0]
    assert f"({trained:.2f} dB against the teacher on trained poses under held-out maps)" in text


def test_readme_quotes_where_the_teacher_env_error_lives():
    """The per-direction study of the OLAT teacher's env-map error, as the README quotes it
    (teacher_directions, three seeds): the per-camera errors, the lit share, the LED-angle
    correlation and camera 1's largest bias are the table's."""
    import numpy as np
    rec = json.loads((RESULTS / "teacher_directions" / "teacher_directions.json").read_text())
    rows = rec["rows"]
    text = " ".join(_docs().split())
    assert sorted({r["seed"] for r in rows}) == [0, 1, 2]
    per_cam = {c: np.mean([r["rel"] for r in rows if r["camera"] == c]) for c in
               ("cam000", "cam001")}
    assert (f"relative squared error of {per_cam['cam000']:.4f} on camera 0 and "
            f"{per_cam['cam001']:.4f} on camera 1") in text
    # "on every seed and under both maps": camera 1 is worse in every (seed, pose, map)
    for r in rows:
        if r["camera"] == "cam001":
            twin = next(x for x in rows if x["seed"] == r["seed"] and x["pose"] == r["pose"]
                        and x["env"] == r["env"] and x["camera"] == "cam000")
            assert r["rel"] > twin["rel"]
    lit = 100 * np.mean([r["places"]["lit"] for r in rows])
    shadowed = 100 * np.mean([r["places"]["shadowed"] for r in rows])
    corr = np.mean([r["corr"] for r in rows])
    assert (f"{lit:.0f} % of it on texels the light reaches, {shadowed:.0f} % in shadow" in text)
    assert f"(correlation {corr:+.2f})" in text and abs(corr) < 0.3
    worst = 100 * max(r["bias"] for r in rows if r["camera"] == "cam001")
    assert f"(up to {worst:+.1f} % too bright there)" in text


def test_readme_quotes_the_shading_teacher_directions():
    """The cpu preset's (shading-input) teacher retrained here and its per-direction
    errors, as the README quotes them (teacher_shading_rerun, teacher_directions_shading)."""
    import numpy as np
    text = " ".join(_docs().split())
    rec = json.loads((RESULTS / "teacher_shading_rerun" / "teacher_inputs.json").read_text())
    res = rec["results"]["shading"]
    gap = res["all_heldout"]["gap"]
    minutes = res["wall_min"] / len(res["seeds"])          # the table's "min per run"
    assert f"held-out gap {gap[0]:.2f} ± {gap[1]:.2f} dB in {minutes:.1f} min per run" in text
    rows = json.loads((RESULTS / "teacher_directions_shading" / "teacher_directions.json")
                      .read_text())["rows"]
    assert {r["teacher"] for r in rows} == {"shading"}
    cams = [np.mean([r["rel"] for r in rows if r["camera"] == c]) for c in ("cam000", "cam001")]
    worst = 100 * max(r["bias"] for r in rows)
    assert (f"{cams[0]:.4f} on camera 0 and {cams[1]:.4f} on camera 1, at most "
            f"{worst:+.1f} % too bright") in text


def test_readme_quotes_the_camera_blind_teacher():
    """``view: none`` against the preset's teacher and its per-direction errors, as the
    README quotes them (teacher_noview, teacher_directions_noview)."""
    import numpy as np
    text = " ".join(_docs().split())
    rec = json.loads((RESULTS / "teacher_noview" / "teacher_inputs.json").read_text())
    assert rec["base"] == "shading"          # stored as versus_paper whatever the base
    versus = rec["results"]["shading_noview"]["versus_paper"]
    held, env = versus["all_heldout"], versus["env"]
    assert (f"({held['diff_db']:+.2f} ± {held['std_db']:.2f} dB, {held['verdict']}), ties "
            f"under env maps ({env['diff_db']:+.2f} ± {env['std_db']:.2f} dB)") in text
    assert held["verdict"] == "worse" and env["verdict"] == "tie"
    rows = json.loads((RESULTS / "teacher_directions_noview" / "teacher_directions.json")
                      .read_text())["rows"]
    cams = [np.mean([r["rel"] for r in rows if r["camera"] == c]) for c in ("cam000", "cam001")]
    assert f"({cams[0]:.4f} on camera 0, {cams[1]:.4f} on camera 1:" in text
    assert cams[1] > 1.5 * cams[0]


def _block(text: str, name: str) -> str:
    return text.split(f"<!-- {name}:start -->\n", 1)[1].split(f"\n<!-- {name}:end -->", 1)[0]


def _tables():
    import sys
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import readme_tables
    return readme_tables


@pytest.mark.skipif(not (RESULTS / "presets" / "presets.json").exists(),
                    reason="no committed presets run")
def test_readme_summary_tables_are_the_committed_results():
    """The README's per-model table and its table of verdicts are what
    benchmarks/readme_tables.py makes from the committed results, and the sentence that
    counts the verdicts counts them."""
    R = _tables()
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert _block(readme, "presets") == R.presets()
    assert _block(readme, "verdicts") == R.verdicts()
    claims = {t: json.loads((RESULTS / f"study_{t}.json").read_text())["claims"]
              for t in R.TABLES}
    small = {t: {c["text"]: c for c in json.loads(
        (RESULTS.parent / f"study_{t}.json").read_text())["claims"]} for t in R.TABLES}
    held = [(t, c) for t, cs in claims.items() for c in cs
            if all(h["verdict"] == "reproduced" for h in c["hands"].values())]
    newly = [c for t, c in held if any(h["verdict"] != "reproduced"
                                       for h in small[t][c["text"]]["hands"].values())]
    total = sum(map(len, claims.values()))
    rows = {r["model"]: r for r in json.loads(
        (RESULTS / "presets" / "presets.json").read_text())["rows"]}
    prose = " ".join(readme.split("<!-- presets:end -->", 1)[1].split(
        "**The papers' claims**", 1)[0].split())
    teacher, student = rows["olat"], rows["student"]
    assert f"the OLAT teacher {teacher['goal']['gap']:.2f} dB below it" in prose
    assert rows["ggx"]["goal"]["gap"] < 0 and rows["linear"]["goal"]["gap"] < 0
    assert (f"the teacher is {teacher['env']['gap']:.2f} dB below, GGX "
            f"{rows['ggx']['env']['gap']:.2f} and the linear model, which renders an env map "
            f"in one pass, {rows['linear']['env']['gap']:.2f}") in prose
    own = student["env"]["gap"] - teacher["env"]["gap"]
    assert (f"is {student['env']['gap']:.2f} dB below: {teacher['env']['gap']:.2f} of it is "
            f"its teacher's error on the same renders, {own:.2f} its own") in prose
    assert f"DRAM stays {rows['dram']['env']['gap']:.2f} dB below" in prose
    after = " ".join(readme.split("<!-- verdicts:end -->", 1)[1].split())
    assert rows["ggx"]["goal"]["psnr"] > teacher["goal"]["psnr"]
    assert (f"({rows['ggx']['goal']['psnr']:.2f} against {teacher['goal']['psnr']:.2f} dB in "
            "the table above)") in after
    said = " ".join(readme.split())
    assert (f"At the `cpu` presets {len(held)} of the {total} claims hold, {len(newly)} of "
            "them") in said
    # Table 2's rerun (issue 53, item 10): its unconverged rows, its student's gap against
    # the cpu student's, and the command that would settle it, named, not run
    t2 = json.loads((RESULTS / "study_rh_t2.json").read_text())
    open_rows = [r for r, hs in t2["convergence"].items()
                 if not all(h["converged"] for h in hs.values())]
    gap = re.search(r"Ours \(student\): right vs GT \+([\d.]+) dB",
                    (RESULTS / "study_rh_t2.md").read_text(encoding="utf-8")).group(1)
    assert (f"{len(open_rows)} of its {len(t2['convergence'])} rows are not converged, and "
            f"its student, Eq. 11's head distilled from the paper-input teacher, sits {gap} dB "
            f"below its ceiling") in said
    assert f"converges {student['env']['gap']:.2f} dB below it" in said
    assert ("`.venv/bin/python benchmarks/study_hands.py --scale converged --seeds 2 --workers 2 "
            "--tables rh_t2 --student cpu --out benchmarks/out/study_converged --results "
            "benchmarks/results/converged/rh_t2_cpu`") in said


def _md_convergence(table: str) -> dict:
    """{(row, hand): converged?} as the committed study_TABLE.md states it in its
    "Convergence (...)" line (the study's own words, read apart from the JSON)."""
    text = (RESULTS / f"study_{table}.md").read_text(encoding="utf-8")
    line = next(x for x in text.splitlines() if x.startswith("Convergence ("))
    found = [re.fullmatch(r"(.+) (right|left) [+-]\d+\.\d+ dB \((NOT converged|converged)\)\.?",
                          part).groups() for part in line.split("): ", 1)[1].split("; ")]
    return {(row, hand): state == "converged" for row, hand, state in found}


def _verdict_hands(cell: str, hands: list) -> dict:
    """{hand: cell text of its verdict} from one cell of the README's verdict table
    (``V``, ``V (h1, h2)`` or ``V: h1, h2; W: h3``)."""
    out = {}
    for group in cell.split("; "):
        m = re.fullmatch(r"(.+?)(?:: (.+)| \(((?:right|left|both)(?:, (?:right|left|both))*)\))?",
                         group)
        named = m.group(2) or m.group(3)
        for hand in (named.split(", ") if named else hands):
            out[hand] = m.group(1)
    return out


def test_no_converged_verdict_rests_on_a_row_that_is_not(tmp_path):
    """README "Do the papers' claims hold?" (issue 53, item 10): a verdict whose rows are
    not all converged (as the committed study_*.md says, row by row) is labelled "not
    converged" on that hand and its rows named; one whose rows all converged is not; no
    column calls verdicts "converged" as a whole; and the sentence under the table counts
    as settled only the claims held on converged rows alone.  The hand ``both`` is scored
    by the right and left rows, so it rests on both."""
    R = _tables()
    block = _block((ROOT / "README.md").read_text(encoding="utf-8"), "verdicts")
    lines = block.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert not any(c.startswith("converged") for c in header), header
    col = next(i for i, c in enumerate(header) if c.startswith("`cpu` presets"))
    rows_col = next(i for i, c in enumerate(header) if c.startswith("the rows it rests on"))
    claims = {}
    for t in R.TABLES:
        rec = json.loads((RESULTS / f"study_{t}.json").read_text())
        for c in rec["claims"]:
            claims[c["text"]] = (t, c)
    seen, settled = 0, []
    states = {t: _md_convergence(t) for t in R.TABLES}
    for line in lines[2:]:
        if not line.startswith("| "):
            break
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        t, claim = claims[cells[0]]
        hands = list(claim["hands"])
        said = _verdict_hands(cells[col], hands)
        assert set(said) == set(hands), (cells[0], said)
        unsettled_rows = set()
        for hand in hands:
            trained = ("right", "left") if hand == "both" else (hand,)
            behind = [(row, h) for row in (claim["better"], claim["worse"]) for h in trained]
            bad = [p for p in behind if not states[t][p]]
            unsettled_rows |= set(bad)
            assert said[hand].endswith(", not converged") == bool(bad), (cells[0], hand, bad)
        for row, hand in unsettled_rows:
            assert f"{row} {hand} (" in cells[rows_col], (cells[0], row, hand)
        if unsettled_rows:
            assert cells[rows_col].startswith(f"rests on {len(unsettled_rows)} of "), cells
        else:
            assert "not converged" not in cells[rows_col], cells
            if all(h["verdict"] == "reproduced" for h in claim["hands"].values()):
                settled.append(claim["text"])
        seen += 1
    assert seen == len(claims) == 19
    said = " ".join(block.split())
    assert f"{len(settled)} of the " in said and "; ".join(settled) in said, settled
    assert len(settled) == 3     # URHand Table 3's three held claims, as committed


def test_the_verdict_table_reads_every_verdict_from_the_results(tmp_path):
    """A verdict moved in a committed table moves the README's cell (the table is read,
    not typed): flip one converged verdict in a copy of the results."""
    import shutil
    R = _tables()
    shutil.copytree(RESULTS.parent, tmp_path / "results",
                    ignore=shutil.ignore_patterns("*.png", "*.md", "*.csv"))
    before = R.verdicts(tmp_path / "results")
    assert before == R.verdicts()
    path = tmp_path / "results" / "converged" / "study_ur_t3.json"
    rec = json.loads(path.read_text())
    claim = next(c for c in rec["claims"] if "refiner" in c["text"])
    claim["hands"]["right"]["verdict"] = "not reproduced (reversed)"
    path.write_text(json.dumps(rec))
    after = R.verdicts(tmp_path / "results")
    row = next(x for x in after.splitlines() if "refiner" in x)
    assert row.endswith("| tie | **reversed** | converged: all 2 rows |") and after != before


def test_the_tables_go_only_where_the_readme_marks_them():
    """readme_tables.put fills the marked block and nothing else; a README without the
    markers is one line and exit 1, the text untouched."""
    R = _tables()
    text = "a\n<!-- x:start -->\nold\n<!-- x:end -->\nb"
    assert R.put(text, "x", "new") == "a\n<!-- x:start -->\nnew\n<!-- x:end -->\nb"
    for broken in ("a\nb", "a\n<!-- x:start -->\nold"):
        with pytest.raises(SystemExit) as e:
            R.put(broken, "x", "new")
        assert str(e.value).startswith("readme_tables.py: error: no <!-- x:start -->")


def test_readme_mitsuba_table_is_the_committed_run():
    """README "The physical renderer, checked against Mitsuba 3": each cell (relative RMS /
    mean ratio) is benchmarks/results/mitsuba.json's row, old defaults and new."""
    record = json.loads((ROOT / "benchmarks" / "results" / "mitsuba.json").read_text())
    rows = {(r["case"], r["env"], r["row"]): r for r in record["rows"]}
    text = (ROOT / "README.md").read_text(encoding="utf-8").split(
        "### The physical renderer, checked against Mitsuba 3", 1)[1].split("### Cameras", 1)[0]
    envs = {"`builtin:sky`": "builtin:sky", "empty_warehouse": "empty_warehouse_01_1k.hdr"}
    seen = 0
    for line in text.splitlines():
        m = re.match(r"\| (diffuse|GGX only \(ρ 0\.45\)), (\S+) \| ([\d.]+) / ([\d.]+) \| "
                     r"([\d.]+) / ([\d.]+) \|", line)
        if not m:
            continue
        case = "diffuse" if m.group(1) == "diffuse" else "specular"
        env = envs[m.group(2)]
        now = ("texels 32x16, sources (= defaults)" if case == "diffuse"
               else "texels 32x16, Smith, sources (= defaults)")
        for label, rel, ratio in (("vertices 32x16 (old CLI default)", m.group(3), m.group(4)),
                                  (now, m.group(5), m.group(6))):
            r = rows[(case, env, label)]
            assert float(rel) == pytest.approx(r["rel_rms"], abs=6e-4), (case, env, label)
            assert float(ratio) == pytest.approx(r["mean_ratio"], abs=6e-3), (case, env, label)
        seen += 1
    assert seen == 4


DGSM = ROOT / "benchmarks" / "results"


@pytest.mark.skipif(not (DGSM / "dgsm.json").exists() or not (DGSM / "dgsm_lighting.json").exists(),
                    reason="no committed DGSM tables")
def test_readme_dgsm_claims_are_the_committed_results():
    """README "Do the papers' claims hold?": the DGSM table is what
    benchmarks/readme_tables.py makes from benchmarks/results/dgsm.json and
    dgsm_lighting.json (issue 49), and the sentences after it count its verdicts."""
    R = _tables()
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert _block(readme, "dgsm") == R.dgsm()
    shadow = json.loads((DGSM / "dgsm.json").read_text())
    light = json.loads((DGSM / "dgsm_lighting.json").read_text())
    assert not shadow["quick"] and not light["quick"]
    assert len(shadow["scenes"]) >= 3 and shadow["speed_seeds"] >= 2
    assert len(light["scenes"]["room"]["clips"]) >= 3
    after = " ".join(readme.split("<!-- dgsm:end -->", 1)[1].split())
    shadow_claims = [c for c in shadow["claims"] if c["table"] != "D"]
    held = sum(c["verdict"] == "reproduced" for c in shadow_claims)
    reversed_ = sum(c["verdict"] == "reversed" for c in shadow_claims)
    assert (f"Of the {len(shadow_claims)} comparisons of Tables 3–5 (one per metric), "
            f"{held} reproduce, {reversed_} reverse") in after
    room = light["scenes"]["room"]["judged"]
    words = ", ".join(f"{label} {room[m]['verdict']}" for m, label in
                      (("paa_y", "PAA-Y"), ("apf_y", "APF-Y"), ("ncm_ab", "NCM-ab")))
    assert f"In the room, relighting: {words}" in after


def test_the_dgsm_table_reads_every_verdict_from_the_results(tmp_path):
    """A verdict moved in a committed DGSM record moves the README's cell."""
    R = _tables()
    if not (DGSM / "dgsm.json").exists() or not (DGSM / "dgsm_lighting.json").exists():
        pytest.skip("no committed DGSM tables")
    for name in ("dgsm.json", "dgsm_lighting.json"):
        (tmp_path / name).write_text((DGSM / name).read_text())
    before = R.dgsm(tmp_path)
    assert before == R.dgsm()
    rec = json.loads((tmp_path / "dgsm.json").read_text())
    claim = next(c for c in rec["claims"] if c["table"] == "Table 5" and c["metric"] == "sae")
    claim["verdict"] = "reversed" if claim["verdict"] != "reversed" else "tie"
    (tmp_path / "dgsm.json").write_text(json.dumps(rec))
    light = json.loads((tmp_path / "dgsm_lighting.json").read_text())
    j = light["scenes"]["room"]["judged"]["paa_y"]
    j["verdict"] = "improves" if j["verdict"] != "improves" else "worsens"
    (tmp_path / "dgsm_lighting.json").write_text(json.dumps(light))
    after = R.dgsm(tmp_path)
    t5 = [x for x in after.splitlines() if "| Table 5 |" in x][0]
    assert t5 != [x for x in before.splitlines() if "| Table 5 |" in x][0]
    paa = [x for x in after.splitlines() if "PAA-Y" in x][0]
    assert paa != [x for x in before.splitlines() if "PAA-Y" in x][0]


IDENTITY = ROOT / "benchmarks" / "results" / "converged" / "study_ur_id.json"


@pytest.mark.skipif(not IDENTITY.exists(), reason="no committed identity study")
def test_readme_identity_claims_are_the_committed_results(tmp_path):
    """README's URHand identity table (issue 51) is what readme_tables.py makes from
    study_ur_id.json (and personalize.json): the unseen subjects are not trained ones,
    every row sits beside its own capture's ceiling, and a verdict's "rows" cell says
    "converged" only when every row it rests on did — a record whose rows did not
    converge is labelled so."""
    R = _tables()
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert _block(readme, "identity") == R.identity()
    record = json.loads(IDENTITY.read_text())
    roles = record["roles"]
    assert len(roles["trained"]) >= 4 and len(roles["unseen"]) >= 2
    assert not set(roles["unseen"]) & set(roles["trained"])
    assert record["seeds"] and len(record["seeds"]) >= 2 and record["checks"]
    for row in record["rows"].values():
        assert row["subject"]["heldout"]["ceiling"]["psnr"]["mean"] is not None
    # flip one row's convergence: the table must say so
    for row in record["convergence"].values():
        for hand in row.values():
            hand["converged"] = True
    (tmp_path / "all.json").write_text(json.dumps(record))
    table = R.identity(tmp_path / "all.json", tmp_path / "none.json")
    assert "not converged" not in table
    first = next(iter(record["convergence"]))
    record["convergence"][first]["subject"]["converged"] = False
    (tmp_path / "one.json").write_text(json.dumps(record))
    table = R.identity(tmp_path / "one.json", tmp_path / "none.json")
    assert f"not converged: {first}" in table.splitlines()[2]
