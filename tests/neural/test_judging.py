"""relight_cli.neural.judging: DESIGN.md's rules for judging a learned model.

Converged (a validation curve that has stopped rising), the verdict (an effect larger than
the seed spread and a minimum size, else a tie: "a 0.01 dB difference is a tie"), the gate
(halfway between the worst measured seed and the sabotage) and a preset's 1-dB goal; each
held to hand-made cases that must fail the wrong way round, and to the committed results
the benchmarks wrote with them.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from conftest import ROOT
from relight_cli.neural import judging as J

NAN = float("nan")
RESULTS = ROOT / "benchmarks" / "results"


# ------------------------------------------------------------------------ statistics


def test_mean_std_is_the_sample_spread_of_the_finite_values():
    s = J.mean_std([1.0, 2.0, 3.0])
    assert s["mean"] == 2.0 and s["std"] == pytest.approx(1.0) and s["n"] == 3
    assert s["values"] == [1.0, 2.0, 3.0]
    # a missing or diverged run is no measurement: left out, not a zero
    s = J.mean_std([1.0, None, NAN, float("inf"), 3.0])
    assert s["n"] == 2 and s["mean"] == 2.0 and s["std"] == pytest.approx(math.sqrt(2))
    assert J.mean_std([4.0]) == {"mean": 4.0, "std": 0.0, "n": 1, "values": [4.0]}
    assert J.mean_std([]) == J.mean_std([None, NAN]) == {"mean": None, "std": None, "n": 0,
                                                          "values": []}


def test_gain_in_db_reads_psnr_as_is_and_an_mse_as_the_log_of_its_ratio():
    assert J.gain_db(28.0, 28.3, "psnr") == pytest.approx(0.3)
    assert J.gain_db(2e-3, 1e-3, "mse") == pytest.approx(10 * math.log10(2))
    assert J.gain_db(1e-3, 2e-3, "mse") == pytest.approx(-10 * math.log10(2))   # got worse
    assert J.gain_db(2e-3, 1e-3, "mae") == pytest.approx(10 * math.log10(2))
    assert J.gain_db(0.8, 0.9, "ssim") is None                # SSIM has no dB
    assert J.gain_db(0.0, 1e-3, "mse") is None and J.gain_db(1e-3, -1.0, "mse") is None
    assert J.gain_db(NAN, 28.0, "psnr") is None and J.gain_db(28.0, None, "psnr") is None


# ------------------------------------------------------------------------ converged


FLAT = [[200, 2.0e-3], [800, 1.02e-3], [1000, 1.0e-3]]          # 0.09 dB in the tail
RISING = [[200, 2.0e-3], [800, 1.5e-3], [1000, 1.0e-3]]         # 1.76 dB in the tail


def test_a_curve_that_still_rises_is_not_converged():
    gain, start = J.tail_gain(RISING, 1000, metric="mse")
    assert start == 800 and gain == pytest.approx(10 * math.log10(1.5))
    assert J.converged([gain]) is False
    gain, _ = J.tail_gain(FLAT, 1000, metric="mse")
    assert gain == pytest.approx(10 * math.log10(1.02)) and J.converged([gain]) is True
    # PSNR: +0.3 dB over the last 20 % still rises; +0.1 has stopped
    assert J.converged([J.tail_gain([[800, 28.0], [1000, 28.3]])[0]]) is False
    assert J.converged([J.tail_gain([[800, 28.0], [1000, 28.1]])[0]]) is True
    # exactly the limit still rises; a falling curve has stopped rising
    assert J.converged([J.CONVERGED_DB]) is False
    assert J.converged([J.tail_gain([[800, 28.0], [1000, 27.0]])[0]]) is True


def test_one_rising_seed_makes_a_row_unconverged_and_an_unknown_one_unknown():
    rising = J.tail_gain(RISING, 1000, metric="mse")[0]
    flat = J.tail_gain(FLAT, 1000, metric="mse")[0]
    assert J.converged([flat, flat]) is True
    assert J.converged([flat, rising]) is False
    assert J.converged([None, rising]) is False          # still rising, whatever the other
    assert J.converged([flat, None]) is None              # cannot say
    assert J.converged([NAN]) is None and J.converged([]) is None


def test_the_tail_is_read_only_where_the_curve_has_points():
    # no point in the last 20 %: unknown, unless validations are sparser than the tail
    assert J.tail_gain([[500, 28.0], [1000, 28.1]]) == (None, None)
    sparse = [[1000, 20.0], [2000, 22.0], [3000, 23.0], [4000, 23.5]]
    gain, start = J.tail_gain(sparse, last_interval=True)
    assert start == 3000 and gain == pytest.approx(0.5)
    assert J.converged([gain]) is False
    # a point inside the tail is used even with last_interval
    gain, start = J.tail_gain([[3000, 23.0], [3500, 23.4], [4000, 23.5]], last_interval=True)
    assert start == 3500 and gain == pytest.approx(0.1)
    # a curve that stops before the run's last iteration, or ends on NaN, says nothing
    assert J.tail_gain([[800, 28.0], [900, 28.1]], 1000) == (None, None)
    assert J.tail_gain([[800, 28.0], [900, 28.1], [1000, NAN]]) == (None, None)
    assert J.tail_gain([[800, 28.0], [900, NAN], [1000, 28.1]]) == (pytest.approx(0.1), 800)
    assert J.tail_gain([]) == (None, None) and J.tail_gain([[1000, 28.0]]) == (None, None)
    assert J.tail_gain([[800, 0.9], [1000, 0.95]], metric="ssim") == (None, None)


# ------------------------------------------------------------------------ verdict


def test_an_effect_larger_than_the_spread_and_the_minimum_is_a_verdict():
    v = J.verdict([0.5, 0.6, 0.4])
    assert v.word == "better" and v.decided and v.n == 3
    assert v.mean == pytest.approx(0.5) and v.margin == pytest.approx(J.MIN_EFFECT_DB)
    assert J.verdict([-0.5, -0.6, -0.4]).word == "worse"
    v = J.verdict([1.0, 1.1])                       # +1.05 ± 0.07 dB: the minimum rules
    assert v.word == "better" and v.margin == J.MIN_EFFECT_DB
    v = J.verdict([1.0, 1.5])                       # +1.25 ± 0.35 dB: the spread rules
    assert v.word == "better" and v.margin == pytest.approx(2 * v.std) and v.margin > 0.7


def test_a_hundredth_of_a_db_is_a_tie():
    """DESIGN.md's own example, with no spread at all and with many seeds."""
    assert J.verdict([0.01, 0.01, 0.01]).word == "tie"
    assert J.verdict([-0.01, -0.01, -0.01]).word == "tie"
    assert J.verdict([0.01 + 1e-6 * i for i in range(10)]).word == "tie"
    v = J.verdict([0.1, 0.1])
    assert v.word == "tie" and not v.decided


def test_an_effect_within_the_seed_spread_is_a_tie():
    v = J.verdict([1.0, -0.5, 1.5])                 # +0.67 dB, but 2σ = 2.08 dB
    assert v.mean > J.MIN_EFFECT_DB and v.word == "tie"
    assert v.margin == pytest.approx(2 * v.std) and v.margin > v.mean
    v = J.verdict([-2.0, 1.0])                      # −0.5 ± 2.1 dB
    assert v.word == "tie" and v.margin > 4
    # exactly the margin is not larger than it
    assert J.verdict([0.2, 0.2]).word == "tie"


def test_one_seed_is_a_tie_however_large():
    v = J.verdict([5.0])
    assert v.word == "tie" and v.n == 1 and v.std == 0.0
    assert J.verdict([5.0, NAN]).word == "tie"       # one finite seed left


def test_non_finite_differences_are_left_out_and_none_is_not_measured():
    v = J.verdict([0.5, NAN, 0.6, None, 0.4])
    assert v.word == "better" and v.n == 3
    for diffs in ([], [NAN, NAN], [None]):
        v = J.verdict(diffs)
        assert v.word == "not measured" and v.n == 0 and v.margin is None
        assert not v.decided


def test_without_a_minimum_the_spread_alone_decides():
    """A metric with no dB reading (SSIM) is judged on 2σ alone: a small effect with no
    spread is then a verdict, one inside the spread still a tie."""
    assert J.verdict([0.01, 0.012, 0.011], min_effect=0.0).word == "better"
    assert J.verdict([0.05, -0.05, 0.1], min_effect=0.0).word == "tie"
    assert J.verdict([0.0, 0.0], min_effect=0.0).word == "tie"


# ------------------------------------------------------------------------ gate


def test_a_gate_lies_halfway_between_the_worst_seed_and_the_sabotage():
    g = J.gate([1.5, 1.2, 1.8], 1.0, "higher")      # MSE ratios against no effect
    assert g.robust and g.worst == 1.2 and g.threshold == pytest.approx(1.1)
    assert all(J.passes(v, g) for v in (1.5, 1.2, 1.8))
    assert J.passes(1.0, g) is False and J.passes(1.1, g) is False     # the sabotage fails
    assert J.passes(NAN, g) is False and J.passes(None, g) is False
    g = J.gate([3.4, 3.5], 5.6, "lower")            # gaps against the untrained model
    assert g.robust and g.worst == 3.5 and g.threshold == pytest.approx(4.55)
    assert J.passes(3.5, g) and not J.passes(5.6, g) and not J.passes(4.55, g)


def test_a_check_whose_seeds_do_not_all_beat_the_sabotage_is_not_gated():
    g = J.gate([1.15, 0.83, 1.57], 1.0, "higher")
    assert not g.robust and g.threshold is None and J.passes(2.0, g) is None
    g = J.gate([3.0, 6.0], 5.6, "lower")            # training did not close the gap
    assert not g.robust and g.threshold is None
    assert not J.gate([1.0, 1.0], 1.0).robust        # no effect at all
    assert not J.gate([], 1.0).robust and not J.gate([1.5, NAN], 1.0).robust
    with pytest.raises(ValueError):
        J.gate([1.5], 1.0, "more")


def test_the_committed_gate_margins_are_the_rule():
    """tests/baseline/study_gate_spread.json (study_hands.py --gate-spread): each check's
    robustness and threshold are what the rule gives from its seeds and its sabotage."""
    spread = json.loads((ROOT / "tests" / "baseline" / "study_gate_spread.json").read_text())
    assert spread["checks"]
    for name, c in spread["checks"].items():
        sabotaged = 1.0 if c["metric"] == "mse_ratio" else c["untrained"]
        g = J.gate(c["values"], sabotaged, c["better"])
        assert g.robust == c["robust"], name
        assert g.worst == c["min" if c["better"] == "higher" else "max"], name
        if c["robust"]:
            assert g.threshold == pytest.approx(c["threshold"], rel=1e-12), name
            assert all(J.passes(v, g) for v in c["values"]) and not J.passes(sabotaged, g)
        else:
            assert c["threshold"] is None and g.threshold is None, name


# ------------------------------------------------------------------------ the goal


def test_a_preset_meets_its_goal_within_one_db_of_its_ceiling():
    assert J.within_goal(0.85) is True and J.within_goal(J.GOAL_DB) is True
    assert J.within_goal(-1.44) is True               # above the ceiling
    assert J.within_goal(1.01) is False and J.within_goal(17.26) is False
    assert J.within_goal(None) is None and J.within_goal(NAN) is None


# ------------------------------------------------------------------------ committed results


def test_the_committed_presets_rows_follow_the_rules():
    """Every row of the committed presets table (bench_presets.py): its tail gain, where
    the tail starts, and converged are the library's reading of its own curve."""
    record = json.loads((RESULTS / "converged" / "presets" / "presets.json").read_text())
    assert len(record["rows"]) == 5
    for r in record["rows"]:
        gain, start = J.tail_gain(r["curve"], r["iters"], last_interval=True)
        assert start == r["tail_from"] and gain == pytest.approx(r["gain_tail_db"]), r["model"]
        assert J.converged([gain]) is r["converged"], r["model"]
    # the students validate every 1,000 of 4,000 iterations: read over the last interval
    assert {r["model"]: r["tail_from"] for r in record["rows"]}["student"] == 3000


def test_the_committed_tables_state_convergence_by_the_rule():
    """Every study table's convergence (study_hands.py): whether each row converged is
    the rule applied to its seeds' tail gains."""
    checked = 0
    for path in sorted(RESULTS.glob("**/study_*.json")):
        record = json.loads(path.read_text())
        for name, per_hand in record.get("convergence", {}).items():
            for hand, c in per_hand.items():
                if c.get("gain_db") and len(c["gain_db"]["values"]) == len(record["seeds"]):
                    assert J.converged(c["gain_db"]["values"]) is c["converged"], \
                        (path.name, name, hand)
                    checked += 1
    assert checked >= 19


# ------------------------------------------------------------------------ the module


def test_the_module_imports_neither_torch_nor_click():
    code = ("import sys; import relight_cli.neural.judging; "
            "print(sorted(m for m in ('torch', 'click') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
