"""World generator: deterministic per seed, routes with clearance, non-Manhattan geometry, parameters
inside the documented ranges; the seed ranges and their guard."""

import math
import tomllib

import numpy as np
import pytest

from glassmap.sim.generate import KINDS, LASER_RANGES, LOOP_LENGTH, MATERIAL_RANGES, MIN_CLEARANCE, generate_world
from glassmap.sim.materials import MaterialKind
from glassmap.sim.seeds import TEST_SEEDS, TRAINING_SEEDS, VALIDATION_SEEDS, TestSeedError, check_not_test, split_of
from glassmap.sim.world import parse_world

SEEDS = range(12)


def test_same_seed_same_world_different_seeds_differ():
    assert generate_world(7).text == generate_world(7).text
    assert generate_world(7).text != generate_world(8).text
    assert generate_world(7, "atrium").text != generate_world(7, "office").text


@pytest.mark.parametrize("seed", SEEDS)
def test_world_parses_and_routes_keep_clearance(seed):
    g = generate_world(seed)
    w = parse_world(g.text)
    assert g.kind == KINDS[seed % len(KINDS)]
    for route in ("loop", "short"):
        assert w.route_clearance(route) >= MIN_CLEARANCE
    wp = w.route("loop")
    length = float(np.hypot(*np.diff(wp, axis=0).T).sum())
    assert LOOP_LENGTH[0] <= length <= LOOP_LENGTH[1]
    assert np.allclose(wp[0], wp[-1])  # a closed loop
    assert (w.segment_kind == MaterialKind.GLASS).any() and (w.segment_kind == MaterialKind.WALL).any()


def test_walls_at_any_angle_and_facetted_curves():
    angles = []
    for seed in SEEDS:
        w = parse_world(generate_world(seed).text)
        d = w.segments[:, 1] - w.segments[:, 0]
        long = np.hypot(d[:, 0], d[:, 1]) > 2.0
        angles.append(np.mod(np.degrees(np.arctan2(d[long, 1], d[long, 0])), 90.0))
    a = np.concatenate(angles)
    off_grid = (a > 2.0) & (a < 88.0)
    assert off_grid.mean() > 0.5  # most long walls are not axis-aligned
    atrium = parse_world(generate_world(3).text)
    assert len(atrium.segments) > 300


def test_distractors_and_clutter_present_across_worlds():
    kinds = set()
    for seed in SEEDS:
        kinds |= set(parse_world(generate_world(seed).text).segment_kind.tolist())
    for k in (MaterialKind.GLASS, MaterialKind.FRAME, MaterialKind.METAL, MaterialKind.WHITEBOARD,
              MaterialKind.RETRO, MaterialKind.DARK, MaterialKind.OBJECT):
        assert int(k) in kinds


@pytest.mark.parametrize("seed", SEEDS)
def test_laser_and_material_parameters_inside_the_documented_ranges(seed):
    doc = tomllib.loads(generate_world(seed).text)
    assert set(doc["laser"]) == set(LASER_RANGES)
    for key, v in doc["laser"].items():
        lo, hi = LASER_RANGES[key]
        assert lo <= v <= hi, key
    for name, fields in MATERIAL_RANGES.items():
        for f, (lo, hi) in fields.items():
            assert lo <= doc["materials"][name][f] <= hi, (name, f)
    w = parse_world(generate_world(seed).text)
    assert w.laser["glass_window"] == pytest.approx(math.radians(doc["laser"]["glass_window_deg"]))


def test_world_laser_parameters_reach_the_laser_model():
    from glassmap.sim.laser import world_laser_params

    w = parse_world(generate_world(1).text)
    p = world_laser_params(w)
    assert p.intensity_scale == w.laser["intensity_scale"] and p.glass_window == w.laser["glass_window"]


def test_seed_ranges_are_disjoint_and_guarded():
    sets = [set(TEST_SEEDS), set(VALIDATION_SEEDS), set(TRAINING_SEEDS)]
    assert not (sets[0] & sets[1]) and not (sets[0] & sets[2]) and not (sets[1] & sets[2])
    assert split_of(0) == "test" and split_of(99) == "test" and split_of(1000) == "validation"
    assert split_of(12345) == "training" and split_of(500) == "unassigned"
    assert check_not_test([1000, 10_000]) == [1000, 10_000]
    with pytest.raises(TestSeedError, match="test-world seeds"):
        check_not_test([10_000, 42])


def test_cli_writes_the_world(tmp_path):
    from runtime.cli import main

    out = tmp_path / "w.toml"
    assert main(["sim", "generate", "--seed", "2", "--out", str(out)]) == 0
    assert out.read_text() == generate_world(2).text
