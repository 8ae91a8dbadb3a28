"""Mirror reflections: a beam reflected by a glass pane or polished metal returns from the surface seen in
the mirror at the unfolded path length (a ghost point behind the mirror), with the reflectance at that
incidence; checked against hand-computed geometry."""

import math

import numpy as np
import pytest

from glassmap.sim.laser import TRUTH_GHOST, LaserParams, simulate_scan
from glassmap.sim.materials import MaterialKind
from glassmap.sim.world import parse_world
from glassmap.types import LaserGeometry

GEOM = LaserGeometry()
# no noise, no weak glass surface return, a low detection threshold so that faint images are seen
EXACT = LaserParams(intensity_noise=0.0, range_noise=0.0, range_noise_slope=0.0, dropout_prob=0.0,
                    saturation=1e12, glass_return_prob=0.0, detection_threshold=0.5)


def beam(deg: float) -> int:
    return int(round((math.radians(deg) - GEOM.angle_min) / GEOM.angle_increment))


def world(mirror_material: str, behind: bool = False):
    # the mirror along y = 1 (segment 0), a wall along y = -2 on the laser's side (segment 1),
    # optionally a wall behind the mirror along y = 3 (segment 2)
    text = ('[[segments]]\na = [-30.0, 1.0]\nb = [30.0, 1.0]\nmaterial = "%s"\n'
            '[[segments]]\na = [-30.0, -2.0]\nb = [30.0, -2.0]\nmaterial = "wall"\n' % mirror_material)
    if behind:
        text += '[[segments]]\na = [-30.0, 3.0]\nb = [30.0, 3.0]\nmaterial = "wall"\n'
    return parse_world(text)


def scan(w, params=EXACT):
    return simulate_scan(w, np.zeros(3), np.random.default_rng(0), params)


@pytest.mark.parametrize("deg", [20.0, 35.0, 60.0])
def test_glass_pane_gives_a_ghost_at_the_mirrored_range(deg):
    s = scan(world("glass"))
    k = beam(deg)
    th = GEOM.angles[k]
    # beam hits y = 1 after 1 / sin(th), reflected, reaches y = -2 after 3 / sin(th) more: 4 / sin(th)
    g = 4.0 / math.sin(th)
    assert s.is_ghost[k] and not s.is_glass[k] and s.truth_class[k] == TRUTH_GHOST
    assert s.ranges[k] == pytest.approx(g, abs=1e-9)
    assert s.true_range[k] == pytest.approx(g, abs=1e-9)
    assert s.mirror_segment[k] == 0 and s.segment[k] == 1 and s.material[k] == MaterialKind.WALL
    # the reported point lies behind the pane, at the wall's mirror image y = 1 + 3 = 4
    assert g * math.sin(th) == pytest.approx(4.0)
    # incidence on the wall: the reflected ray (cos th, -sin th) against the normal (0, 1)
    assert s.incidence[k] == pytest.approx(math.pi / 2 - th, abs=1e-9)
    # intensity: K (r0 / g) R(alpha)^2 rho cos(alpha_wall), R by Schlick with R0 = 0.04 at the pane's
    # incidence alpha = 90 deg - th (cos alpha = sin th)
    r = 0.04 + 0.96 * (1.0 - math.sin(th)) ** 5
    expected = 6000.0 / g * r * r * 0.65 * math.sin(th)
    assert s.intensities[k] == pytest.approx(expected, rel=1e-9)


def test_glass_image_is_brighter_at_grazing_incidence():
    s = scan(world("glass"))
    assert s.intensities[beam(15.0)] > s.intensities[beam(45.0)] > 0


def test_image_is_below_the_threshold_with_default_parameters_near_normal_incidence():
    s = scan(world("glass"), LaserParams(intensity_noise=0.0, glass_return_prob=0.0, dropout_prob=0.0))
    k = beam(80.0)  # incidence 10 deg: R = 0.04, R^2 = 0.0016: far too faint to be seen
    assert not s.is_ghost[k]


def test_metal_returns_first_and_its_image_is_the_last_echo():
    s = scan(world("metal"))
    k = beam(30.0)
    th = GEOM.angles[k]
    assert not s.is_ghost[k] and s.material[k] == MaterialKind.METAL
    assert s.ranges[k] == pytest.approx(1.0 / math.sin(th), abs=1e-9)
    g = 4.0 / math.sin(th)
    assert s.echo_ranges[k, 1] == pytest.approx(g, abs=1e-9)
    # metal mirrors half the power at every angle: K (r0 / g) 0.5^2 rho cos(alpha_wall)
    assert s.echo_intensities[k, 1] == pytest.approx(6000.0 / g * 0.25 * 0.65 * math.sin(th), rel=1e-9)


def test_wall_behind_the_pane_is_nearer_than_the_image():
    s = scan(world("glass", behind=True))
    k = beam(40.0)
    th = GEOM.angles[k]
    assert not s.is_ghost[k] and s.segment[k] == 2 and s.crossed_glass[k]
    assert s.ranges[k] == pytest.approx(3.0 / math.sin(th), abs=1e-9)
    assert s.echo_ranges[k, 1] == pytest.approx(4.0 / math.sin(th), abs=1e-9)


def test_mirror_reflections_can_be_switched_off():
    from dataclasses import replace

    s = scan(world("glass"), replace(EXACT, mirror_reflections=False))
    assert not s.is_ghost.any() and (s.mirror_segment == -1).all()
    assert np.isinf(s.ranges[beam(30.0)])


def test_office_has_ghosts_labelled_as_not_glass():
    from glassmap.sim.world import load_world

    w = load_world("office")
    rng = np.random.default_rng(1)
    ghosts = 0
    for x in np.linspace(3.0, 33.0, 6):
        s = simulate_scan(w, np.array([x, 1.2, 0.0]), rng)
        ghosts += int(s.is_ghost.sum())
        assert not (s.is_ghost & s.is_glass).any()
        assert (s.mirror_segment[s.is_ghost] >= 0).all() and (s.mirror_segment[~s.is_ghost] == -1).all()
    assert ghosts > 0
