"""relight_cli.jobs.score_capture: the record says what the evaluator scored."""

from __future__ import annotations


def test_score_capture_records_what_the_evaluator_scored(monkeypatch):
    """score_capture over a stand-in CaptureEvaluator: its default splits, at most
    eval_samples per split on the bar, its scores, and the settings the metrics keep."""
    from types import SimpleNamespace

    from relight_cli.jobs import score_capture as S
    from relight_cli.neural import evaluate as EV
    calls = []

    class Evaluator:
        def __init__(self, capture, models, device, aa, env_res):
            self.aa, self.names, self.models = aa or 2, ["right"], models
            self.sampling = {"matched": False, "capture_aa": 1}
            self.data = SimpleNamespace(splits=lambda: {"heldout": [1, 2, 3], "env": [4]})

        def default_splits(self):
            return ["heldout", "env"]

        def evaluate(self, splits, max_samples, progress=None):
            calls.append((splits, max_samples))
            for _ in range(sum(min(max_samples or 9, n) for n in (3, 1))):
                progress(1)
            return {s: {"mse": 0.5} for s in splits}

    monkeypatch.setattr(EV, "CaptureEvaluator", Evaluator)
    model = SimpleNamespace(name="t.pt", model_name="teacher", sides=["right"], step=7,
                            subject=None)
    said = []
    out = S.score_capture("cap", [model], S.CaptureOptions(eval_samples=2, env_res=(4, 8)),
                          log=said.append)
    assert calls == [(["heldout", "env"], 2)]
    assert out.scores == {"heldout": {"mse": 0.5}, "env": {"mse": 0.5}}
    assert list(out.settings) == ["model", "splits", "eval_samples", "env_res", "aa",
                                  "sampling", "hands"]
    assert out.settings["env_res"] == [4, 8] and out.settings["aa"] == 2
    assert out.settings["hands"] == [{"hand": 0, "name": "right", "checkpoint": "t.pt",
                                      "model": "teacher", "sides": ["right"], "step": 7}]
    assert len(said) == 1 and "sampled 2×2" in said[0]
