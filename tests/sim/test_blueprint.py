"""Blueprint rasterisation: known segments land in known cells with the right label."""

import numpy as np

from glassmap.sim.blueprint import FREE, GLASS, WALL, Blueprint
from glassmap.sim.world import load_world, parse_world

W = parse_world("""
[[segments]]
a = [0.02, 0.02]
b = [0.98, 0.02]
material = "wall"
[[segments]]
a = [0.02, 0.52]
b = [0.98, 0.52]
material = "glass"
[[segments]]
a = [0.52, 0.53]
b = [0.53, 0.53]
material = "frame"
""")


def test_known_cells():
    bp = Blueprint.from_world(W, resolution=0.05, margin=0.0)
    np.testing.assert_allclose(bp.origin, [0.0, 0.0])
    assert bp.resolution == 0.05
    assert bp.shape == (11, 20)
    assert np.all(bp.labels[0, :] == WALL)  # y = 0.02 -> row 0, x 0.02..0.98 -> all 20 columns
    assert np.all(bp.labels[10, :] == GLASS)  # y = 0.52 -> row 10; a 1 cm frame bit does not win the cell
    assert np.all(bp.labels[1:10] == FREE)
    np.testing.assert_array_equal(bp.cell_of([[0.52, 0.52], [0.01, 0.99]]), [[10, 10], [19, 0]])
    assert bp.to_rgb().shape == (11, 20, 3)


def test_matching_another_grid_and_png(tmp_path):
    bp = Blueprint.from_world(W, resolution=0.1, origin=(-1.0, -1.0), shape=(40, 30))
    assert bp.shape == (40, 30)
    r, c = bp.cell_of([0.5, 0.52])
    assert bp.labels[r, c] == GLASS
    path = bp.save_png(tmp_path / "bp.png")
    assert path.stat().st_size > 100


def test_office_blueprint_has_glass_and_walls():
    bp = Blueprint.from_world(load_world("office"))
    counts = np.bincount(bp.labels.ravel(), minlength=3)
    assert counts[GLASS] > 40 / 0.05 * 0.8  # > 40 m of glass
    assert counts[WALL] > counts[GLASS]
    assert bp.labels[tuple(bp.cell_of([5.0, 1.2]))] == FREE  # the corridor
    assert bp.labels[tuple(bp.cell_of([5.7, 2.4]))] == GLASS
    assert bp.labels[tuple(bp.cell_of([5.0, 2.4]))] == WALL  # a mullion between two panes
