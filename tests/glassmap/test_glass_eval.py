"""Scoring classifiers without retraining: on test worlds (JSON out) and on labelled beams."""

from __future__ import annotations

import json
import math

import numpy as np

from glassmap.glass_eval import per_world, score, summarise


def test_eval_command_scores_both_models_on_the_same_test_world_beams(tmp_path, capsys):
    from runtime.cli import main

    out = tmp_path / "ev"
    assert main(["glass", "eval", "--generated", "1", "--builtin", "room", "--scans", "3", "--out", str(out),
                 "--no-progress"]) == 0
    res = json.loads((out / "eval.json").read_text())  # strict JSON: NaN written as null
    assert set(res["models"]) == {"context", "baseline"}
    assert res["config"]["generated_test_worlds"] == 1
    for m in res["models"].values():
        worlds = {w["world"]: w for w in m["worlds"]}
        assert len(worlds) == 2 and "room" in worlds
        assert worlds["room"]["n_glass"] == 0 and worlds["room"]["balanced_accuracy"] is None
        assert 0 <= worlds["room"]["false_glass_rate"] <= 1
        assert m["summary"]["n_worlds"] == 2 and m["summary"]["n_worlds_with_glass"] == 1
    n = {k: [w["n"] for w in m["worlds"]] for k, m in res["models"].items()}
    assert n["context"] == n["baseline"]  # the same beams for both
    assert "context" in capsys.readouterr().out


def test_summary_is_over_worlds_and_skips_undefined_figures():
    rng = np.random.default_rng(0)
    y = rng.uniform(size=400) < 0.2
    good = score(y, np.where(y, 0.9, 0.1))
    bad = score(y, np.where(y, 0.6, 0.4 + 0.2 * (rng.uniform(size=400) < 0.3)))
    empty = score(np.zeros(50, bool), np.full(50, 0.2))
    assert math.isnan(empty["balanced_accuracy"]) and empty["false_glass_rate"] == 0.0
    rows = per_world([{"world": "a", "seed": 0, **good}, {"world": "a", "seed": 1, **good},
                      {"world": "b", "seed": 0, **bad}, {"world": "c", "seed": 0, **empty}])
    assert [r["world"] for r in rows] == ["a", "b", "c"] and rows[0]["seeds"] == 2
    s = summarise(rows)
    assert s["n_worlds"] == 3 and s["worst_world"] == "b"
    assert s["balanced_accuracy_mean"] == (good["balanced_accuracy"] + bad["balanced_accuracy"]) / 2
    assert s["precision_worst"] == bad["precision"]
