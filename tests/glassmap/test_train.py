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
    clf, info = train_classifier(data, TrainConfig(epochs=8, batch_size=256, lr=1e-2), log=lambda *_: None)
    assert info["validation"]["balanced_accuracy"] > 0.9
    p = clf.predict(np.expm1(np.array([8.0, 8.0, 2.0])), np.array([2.0, 2.0, 2.0]), np.array([0.05, 1.2, 0.05]))
    assert p[0] > 0.5 and p[1] < 0.5 and p[2] < 0.5
