"""End to end, as a user with a new sensor would: record two demo runs with laser parameters well outside
the shipped models' training range, label both from the world file (the floor plan), train on one, score
on the other. The retrained model must beat the shipped one on the recording it did not train on.
Slow (two emulated runs, labelling, training): ``scripts/dev.sh slow``."""

from __future__ import annotations

import asyncio
import json
from importlib import resources

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

# a "new sensor": every value outside the generated worlds' laser ranges (glassmap.sim.generate.LASER_RANGES)
NEW_SENSOR = """
[laser]
intensity_scale = 2500.0
range_exponent = 1.35
cos_exponent = 2.0
intensity_noise = 0.28
detection_threshold = 20.0
glass_window_deg = 6.0
glass_return_prob = 0.5
"""


def test_retraining_on_a_labelled_recording_beats_the_shipped_model(tmp_path, capsys):
    from glassmap.sim.generate import LASER_RANGES
    from runtime.cli import main
    from runtime.demo import DemoOptions, run_demo

    world = tmp_path / "office-new-sensor.toml"
    world.write_text((resources.files("glassmap") / "worlds" / "office.toml").read_text() + NEW_SENSOR)
    for key, (lo, hi) in (("intensity_scale", LASER_RANGES["intensity_scale"]),
                          ("cos_exponent", LASER_RANGES["cos_exponent"]),
                          ("glass_window_deg", LASER_RANGES["glass_window_deg"])):
        v = float(NEW_SENSOR.split(f"{key} = ")[1].split()[0])
        assert not lo <= v <= hi

    labels = []
    for seed in (1, 2):
        out = tmp_path / f"run{seed}"
        res = asyncio.run(run_demo(DemoOptions(world=str(world), route="short", speed=2.0, duration=12.0,
                                               seed=seed, out_dir=str(out), progress=False)))
        assert res.recording and res.summary.stages.scans_received > 100  # all received scans are recorded
        lab = tmp_path / f"run{seed}.npz"
        assert main(["glass", "label", res.recording, "--world", str(world), "--initial-pose", "1.2,1.2,0",
                     "--out", str(lab), "--no-progress"]) == 0
        text = capsys.readouterr().out
        assert "multi-echo: yes" in text  # the runtime streamed and recorded multi-echo scans
        labels.append(str(lab))

    trained = tmp_path / "trained"
    assert main(["glass", "train", "--labelled", labels[0], "--fine-tune", "--model", "context", "--epochs", "8",
                 "--out", str(trained), "--no-progress"]) == 0
    capsys.readouterr()
    out = tmp_path / "eval"
    assert main(["glass", "eval", "--labelled", labels[1], "--models", f"context,{trained / 'glass_context'}",
                 "--out", str(out), "--no-progress"]) == 0
    res = json.loads((out / "eval.json").read_text())["models"]
    shipped, new = res["context"]["summary"], res[str(trained / "glass_context")]["summary"]
    assert shipped["n_glass"] > 200
    gain_bacc = new["balanced_accuracy"] - shipped["balanced_accuracy"]
    gain_prec = new["precision"] - shipped["precision"]
    with capsys.disabled():
        print(f"\nnew sensor, held-out recording ({shipped['n']} beams, {shipped['n_glass']} glass): shipped "
              f"context balanced accuracy {shipped['balanced_accuracy']:.4f}, precision {shipped['precision']:.4f}; "
              f"fine-tuned {new['balanced_accuracy']:.4f}, {new['precision']:.4f} "
              f"(+{gain_bacc:.4f} balanced accuracy, +{gain_prec:.4f} precision)")
    assert gain_bacc > 0 and gain_prec > 0.1
