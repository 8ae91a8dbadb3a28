"""The shipped classifiers (context and baseline) load without network and separate simulated glass from
wall beams; the context model beats the baseline on the same beams."""

import json
import math
import shutil

import numpy as np
import pytest

from glassmap.angles import incidence_angles
from glassmap.classifier import ClassifierError, GlassClassifier
from glassmap.eval.metrics import binary_report


@pytest.fixture(scope="module")
def clf():
    return GlassClassifier.load_default()


@pytest.fixture(scope="module")
def base():
    return GlassClassifier.load_default("baseline")


def test_shipped_weights_are_small_and_load(clf, base):
    from glassmap.classifier import MODEL_DIR

    for m in ("context", "baseline"):
        assert (MODEL_DIR / f"glass_{m}.pt").stat().st_size < 200_000
    assert clf.model_name == "context" and clf.uses_echoes
    assert base.model_name == "baseline" and not base.uses_echoes
    assert base.meta.feature_names == ("log1p(intensity)", "distance_m", "incidence_rad")
    assert clf.meta.feature_names[:3] == base.meta.feature_names
    for c in (clf, base):
        assert len([m for m in c.model if m.__class__.__name__ == "Linear"]) == 4
        assert c.meta.temperature > 0
        assert c.meta.report["train_seeds"] and c.meta.report["val_seeds"]


def test_known_beams(base):
    # a saturated return at normal incidence at 2 m: the specular glass peak
    p = base.predict(np.array([12000.0, 800.0]), np.array([2.0, 2.0]), np.array([0.0, math.radians(40)]))
    assert p[0] > 0.5 > p[1]
    assert p.shape == (2,) and np.all((p > 0) & (p < 1))


@pytest.mark.parametrize("world_name", ["office", "lobby"])
def test_classifies_simulated_glass_and_wall_beams(clf, base, world_name):
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses

    world = load_world(world_name)
    rng = np.random.default_rng(7)
    ys, pc, pb = [], [], []
    for pose in sample_poses(world, 25, rng):
        sim = simulate_scan(world, pose, rng)
        scan = sim.to_scan()
        inc = incidence_angles(scan.angles, scan.ranges)
        use = np.isfinite(inc.incidence) & np.isfinite(scan.ranges)
        pc.append(clf.predict_scan(scan, inc, use))
        pb.append(base.predict_scan(scan, inc, use))
        # the baseline through predict_scan is the paper's f(i, d, theta)
        np.testing.assert_allclose(pb[-1], base.predict(scan.intensities[use], scan.ranges[use],
                                                        inc.incidence[use]), rtol=1e-6)
        ys.append(sim.is_glass[use])
    y = np.concatenate(ys)
    rc, rb = binary_report(y, np.concatenate(pc)), binary_report(y, np.concatenate(pb))
    assert y.sum() > 20
    assert rc.roc_auc > 0.99 and rc.balanced_accuracy > 0.95
    assert rb.roc_auc > 0.9 and rb.balanced_accuracy > 0.8
    assert rc.balanced_accuracy > rb.balanced_accuracy and rc.precision > rb.precision


def test_bad_inputs(clf, base, tmp_path):
    with pytest.raises(ValueError):
        base.predict(np.ones(3), np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match="finite"):
        base.predict(np.array([np.nan]), np.array([1.0]), np.array([0.1]))
    assert base.predict(np.zeros(0), np.zeros(0), np.zeros(0)).shape == (0,)
    with pytest.raises(ClassifierError, match="baseline"):
        clf.predict(np.ones(1), np.ones(1), np.ones(1))  # the context model needs whole scans
    with pytest.raises(ClassifierError, match="glassmap glass train"):
        GlassClassifier.load(tmp_path / "missing")
    with pytest.raises(ClassifierError, match="shipped models"):
        GlassClassifier.load_default("nonsense")


def test_metadata_must_name_a_known_model(tmp_path):
    from glassmap.classifier import shipped_stem

    src = shipped_stem("baseline")
    shutil.copy(src.with_suffix(".pt"), tmp_path / "m.pt")
    meta = json.loads(src.with_suffix(".json").read_text())
    meta["feature_names"] = ["log1p(intensity)", "distance_m"]
    (tmp_path / "m.json").write_text(json.dumps(meta))
    with pytest.raises(ClassifierError, match="not a known model"):
        GlassClassifier.load(tmp_path / "m")


@pytest.mark.parametrize("model", ["context", "baseline"])
def test_numpy_inference_matches_the_torch_network(model):
    """The shipped .npz holds the .pt's weights, and the numpy network gives the torch network's p(glass)
    up to float32 rounding (different summation order in the products)."""
    import torch

    from glassmap.classifier import shipped_stem

    stem = shipped_stem(model)
    from_npz = GlassClassifier.load(stem)
    state = torch.load(stem.with_suffix(".pt"), map_location="cpu", weights_only=True)
    for j, (w, b) in enumerate(from_npz.layers):
        tw, tb = state[f"{2 * j}.weight"].numpy().copy(), state[f"{2 * j}.bias"].numpy().copy()
        tw[np.abs(tw) < 1e-30] = 0.0  # denormals zeroed at load
        tb[np.abs(tb) < 1e-30] = 0.0
        np.testing.assert_array_equal(w, tw)
        np.testing.assert_array_equal(b, tb)
    meta = from_npz.meta
    x = (np.random.default_rng(3).normal(size=(4000, len(meta.feature_names))) * meta.std + meta.mean).astype(np.float32)
    with torch.inference_mode():
        z = torch.from_numpy(((x - np.float32(meta.mean)) / np.float32(meta.std)).astype(np.float32))
        lg = from_npz.model(z).numpy().astype(np.float64) / meta.temperature
    p_torch = 1.0 / (1.0 + np.exp(-(lg[:, 1] - lg[:, 0])))
    np.testing.assert_allclose(from_npz.predict_features(x), p_torch, rtol=0, atol=1e-5)


def test_loads_from_a_torch_state_dict_alone_and_refuses_wrong_shapes(tmp_path):
    from glassmap.classifier import shipped_stem

    src = shipped_stem("baseline")
    shutil.copy(src.with_suffix(".pt"), tmp_path / "m.pt")
    shutil.copy(src.with_suffix(".json"), tmp_path / "m.json")
    x = np.array([[8.0, 2.0, 0.1], [6.0, 5.0, 0.9]], dtype=np.float32)
    ref = GlassClassifier.load(src).predict_features(x)
    np.testing.assert_array_equal(GlassClassifier.load(tmp_path / "m").predict_features(x), ref)
    clf = GlassClassifier.load(src)
    layers = clf.layers
    layers[1] = (layers[1][0][:, :5], layers[1][1])
    np.savez(tmp_path / "m.npz", **{f"{k}{j}": a for j, (w, b) in enumerate(layers) for k, a in (("w", w), ("b", b))})
    with pytest.raises(ClassifierError, match="do not match the architecture"):
        GlassClassifier.load(tmp_path / "m")


def test_the_runtime_path_does_not_load_torch():
    """Loading and running the shipped classifier needs numpy only (torch alone is ~230 MiB resident)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from glassmap.classifier import GlassClassifier\n"
            "c = GlassClassifier.load_default()\n"
            "c.predict_features(np.zeros((3, len(c.meta.feature_names)), np.float32))\n"
            "print('torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_maps_with_the_numpy_network_match_the_torch_network():
    """The glass path over a simulated stretch of the office, once with the numpy network and once with the
    torch module of the same weights: the occupancy grid is identical, the glass map agrees to float32
    rounding of the logits (issue 19's accuracy check of the numpy inference)."""
    import torch

    from glassmap.mapping import GlassMapper
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world

    class TorchNetwork(GlassClassifier):
        def logits(self, x):
            z = ((np.asarray(x, np.float32) - self._mean) * self._inv_std).astype(np.float32)
            with torch.inference_mode():
                return self._net(torch.from_numpy(z)).numpy() * np.float32(self._inv_t)

    shipped = GlassClassifier.load_default()
    ref = TorchNetwork(shipped.layers, shipped.meta)
    ref._net = shipped.model
    world = load_world("office")
    way = world.route()
    mappers = [GlassMapper(classifier=c) for c in (shipped, ref)]
    rng = np.random.default_rng(5)
    for i in range(40):
        a, b = way[i % (len(way) - 1)], way[i % (len(way) - 1) + 1]
        xy = a + (b - a) * ((i % 7) / 7.0)
        pose = np.array([xy[0], xy[1], math.atan2(b[1] - a[1], b[0] - a[0])])
        scan = simulate_scan(world, pose, rng).to_scan(stamp=0.025 * i, seq=i)
        for m in mappers:
            m.process(scan, pose, 0.02)
    (g0, g1) = [m.grid for m in mappers]
    np.testing.assert_array_equal(g0["occupancy"], g1["occupancy"])
    np.testing.assert_array_equal(np.isnan(mappers[0].confidence_map()), np.isnan(mappers[1].confidence_map()))
    assert np.abs(mappers[0].glass.log_odds - mappers[1].glass.log_odds).max() < 1e-4
    assert mappers[0].glass.log_odds.any()  # glass was seen


@pytest.mark.parametrize("model", ["baseline", "context"])
def test_compiled_passes_give_the_numpy_logits_bit_for_bit(model):
    """The standardisation and bias + ReLU passes are compiled; the logits equal those of the plain numpy
    passes exactly (features around the training distribution, exact zeros, a non-contiguous float64 input)."""
    c = GlassClassifier.load_default(model)
    rng = np.random.default_rng(3)
    k = len(c.meta.feature_names)
    x = (rng.normal(size=(700, k)) * np.asarray(c.meta.std) * 2 + np.asarray(c.meta.mean)).astype(np.float32)
    x[:50] = 0.0
    x[50:60] = np.asarray(c.meta.mean, dtype=np.float32)  # standardised to exact zeros

    def numpy_logits(x):
        h = (np.asarray(x, dtype=np.float32) - c._mean) * c._inv_std
        for j, (wt, b) in enumerate(c._layers):
            h = h @ wt
            h += b
            if j < len(c._layers) - 1:
                np.maximum(h, 0.0, out=h)
        return h * np.float32(c._inv_t)

    assert np.array_equal(c.logits(x), numpy_logits(x))
    wide = np.asfortranarray(x.astype(np.float64))
    assert np.array_equal(c.logits(wide), numpy_logits(wide))
    assert c.logits(x[:0]).shape == (0, 2)


def test_predict_scan_is_predict_features_of_the_rows_to_the_bit(clf, base):
    """predict_scan standardises the rows ``use`` in place of copying them (classifier_jit.standardise_rows)
    and takes the softmax from the logits' gap (negative_logit_gaps): the numbers of the numpy code it
    replaced, ``1 / (1 + exp(-(l1 - l0)))`` of ``logits(x[use])``; non-finite inputs are still refused."""
    from glassmap.glass_features import scan_features
    from glassmap.sim.laser import simulate_scan
    from glassmap.sim.world import load_world
    from glassmap.train import sample_poses

    world = load_world("office")
    rng = np.random.default_rng(3)
    for pose in sample_poses(world, 6, rng):
        scan = simulate_scan(world, pose, rng).to_scan()
        inc = incidence_angles(scan.angles, scan.ranges)
        use = np.isfinite(inc.incidence) & np.isfinite(scan.ranges)
        for c in (clf, base):
            x = scan_features(c.meta.model, scan.angles, scan.ranges, scan.intensities, inc, scan.echoes,
                              scan.echo_intensities)[use]
            lg = c.logits(x).astype(np.float64)
            np.testing.assert_array_equal(c.predict_scan(scan, inc, use), 1.0 / (1.0 + np.exp(-(lg[:, 1] - lg[:, 0]))))
            np.testing.assert_array_equal(c.predict_features(x), c.predict_scan(scan, inc, use))
    assert clf.predict_scan(scan, inc, np.zeros_like(use)).shape == (0,)
    scan.intensities[np.flatnonzero(use)[0] + 1] = np.inf  # a neighbour's intensity: not finite features
    with pytest.raises(ValueError, match="finite"):
        clf.predict_scan(scan, inc, use)
