"""Training loop and temperature scaling on synthetic arrays (no simulator)."""

import numpy as np
import pytest

from glassmap.train import BeamSet, TrainConfig, fit_temperature, train_classifier


def test_fit_temperature_recovers_known_temperature():
    rng = np.random.default_rng(0)
    z = rng.normal(0, 2.0, 40_000)
    y = rng.uniform(size=z.size) < 1 / (1 + np.exp(-z))
    t = fit_temperature(2.5 * z, y, np.ones(z.size))  # logits 2.5x too confident
    assert abs(t - 2.5) < 0.15


@pytest.fixture
def one_thread():
    """Tiny matrices: threads only add contention on a busy machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_training_loop_learns_a_separable_rule(one_thread):
    rng = np.random.default_rng(1)
    n = 6000
    inten = rng.uniform(0, 9, n)  # log1p(intensity)
    dist = rng.uniform(0.5, 10, n)
    inc = rng.uniform(0, 1.5, n)
    y = (inc < 0.2) & (inten > 6)  # "glass": bright near normal incidence
    data = BeamSet(np.column_stack([inten, dist, inc]).astype(np.float32), y, np.zeros(n))
    clf, info = train_classifier(data, TrainConfig(model="baseline", epochs=8, batch_size=256, lr=1e-2),
                                 log=lambda *_: None)
    assert info["validation"]["balanced_accuracy"] > 0.9
    p = clf.predict(np.expm1(np.array([8.0, 8.0, 2.0])), np.array([2.0, 2.0, 2.0]), np.array([0.05, 1.2, 0.05]))
    assert p[0] > 0.5 and p[1] < 0.5 and p[2] < 0.5


def test_training_refuses_test_world_seeds():
    from glassmap.sim.seeds import TestSeedError
    from glassmap.train import simulate_worlds

    with pytest.raises(TestSeedError, match="test-world seeds"):
        simulate_worlds([10_000, 42], 2, 0)
    with pytest.raises(TestSeedError):
        simulate_worlds([7], 2, 0, purpose="validation (early stopping and calibration)")


def test_train_command_refuses_test_seeds_and_keeps_the_shipped_weights(capsys):
    from glassmap.classifier import shipped_stem
    from runtime.cli import main

    before = shipped_stem("context").with_suffix(".pt").read_bytes()
    assert main(["glass", "train", "--train-seeds", "0-3", "--no-progress"]) == 2
    assert "test-world seeds" in capsys.readouterr().err
    assert main(["glass", "train", "--val-seeds", "99", "--no-progress"]) == 2
    assert shipped_stem("context").with_suffix(".pt").read_bytes() == before


def test_tiny_context_training_on_generated_worlds_then_fine_tuning(one_thread, tmp_path):
    from glassmap.classifier import GlassClassifier
    from glassmap.train import run_training, save_classifier, simulate_worlds

    train = simulate_worlds([10_000, 10_001], 6, 0)
    val = simulate_worlds([1000], 4, 1, purpose="validation")
    assert train.x.shape[1] == 19 and train.y.any() and set(np.unique(train.group)) == {0, 1}
    cfg = TrainConfig(model="context", epochs=3, batch_size=512)
    rep = run_training(cfg, out_stem=tmp_path / "ctx", progress=False, log=lambda *_: None, data=(train, val))
    clf = GlassClassifier.load(tmp_path / "ctx")
    assert clf.model_name == "context" and clf.uses_echoes
    assert rep["train"]["validation"]["roc_auc"] > 0.9
    p = clf.predict_beams(val.x)
    assert p.shape == val.y.shape and np.mean(p[val.y]) > np.mean(p[~val.y])

    start = [w.detach().clone() for w in clf.model.parameters()]
    tuned, info = train_classifier(train, TrainConfig(model="context", epochs=1, batch_size=512), val=val,
                                   init=clf, log=lambda *_: None)
    assert info["fine_tuned"] and tuned.meta.mean == clf.meta.mean  # the normalisation is kept
    assert any(not np.allclose(a.numpy(), b.detach().numpy()) for a, b in zip(start, tuned.model.parameters()))
    save_classifier(tuned, tmp_path / "tuned")
    assert GlassClassifier.load(tmp_path / "tuned").model_name == "context"
    with pytest.raises(ValueError, match="fine-tune"):
        train_classifier(train, TrainConfig(model="baseline", epochs=1), val=val, init=clf)
