"""World files: built-in worlds load and their routes keep clear of walls; bad files give clear errors."""

import math
from pathlib import Path

import numpy as np
import pytest

from glassmap.sim.materials import MaterialKind
from glassmap.sim.world import RouteError, WorldFileError, builtin_worlds, load_world, parse_world

GOOD = """
name = "tiny"
[start]
x = 1.0
y = 1.0
yaw_deg = 90
[materials.shiny]
kind = "metal"
lobe_width_deg = 2.0
[[segments]]
a = [0.0, 0.0]
b = [4.0, 0.0]
material = "wall"
[[panes]]
a = [0.0, 3.0]
b = [4.0, 3.0]
pane_width = 2.0
frame_width = 0.1
frame_depth = 0.0
[[boxes]]
center = [2.0, 1.5]
size = [1.0, 0.5]
material = "shiny"
[routes.r]
waypoints = [[0.5, 1.0], [3.5, 1.0]]
"""


def test_builtin_worlds_are_shipped():
    assert {"office", "glass-corridor", "room", "lobby"} <= set(builtin_worlds())


@pytest.mark.parametrize("name", ["office", "glass-corridor", "room", "lobby"])
def test_every_route_keeps_0_4_m_clear_of_walls(name):
    w = load_world(name)
    assert w.routes, name
    for r in w.routes:
        assert w.route_clearance(r) >= 0.4, (name, r)


def test_office_has_glass_facade_partitions_and_distractors():
    w = load_world("office")
    kinds = set(np.unique(w.segment_kind).tolist())
    for k in (MaterialKind.WALL, MaterialKind.GLASS, MaterialKind.FRAME, MaterialKind.METAL,
              MaterialKind.WHITEBOARD, MaterialKind.RETRO, MaterialKind.DARK):
        assert int(k) in kinds, k.name
    glass_len = np.hypot(*(w.segments[w.segment_is_glass, 1] - w.segments[w.segment_is_glass, 0]).T).sum()
    assert glass_len > 40.0  # a long facade plus partitions and doors
    (x0, _), (x1, _) = w.bounds
    assert 25.0 <= x1 - x0 <= 45.0


def test_room_has_no_glass():
    assert not load_world("room").segment_is_glass.any()


def test_parse_builds_panes_boxes_and_routes():
    w = parse_world(GOOD)
    assert w.name == "tiny"
    np.testing.assert_allclose(w.start_pose, [1.0, 1.0, math.pi / 2])
    # panes: 4 m wide, 2 panes of (4 - 3 * 0.1) / 2 = 1.85 m and 3 flat frames of 0.1 m
    glass = w.segments[w.segment_is_glass]
    assert len(glass) == 2
    np.testing.assert_allclose(np.hypot(*(glass[:, 1] - glass[:, 0]).T), [1.85, 1.85])
    assert (w.segment_kind == int(MaterialKind.FRAME)).sum() == 3
    assert (w.segment_kind == int(MaterialKind.METAL)).sum() == 4
    assert w.material_named("shiny").lobe_width == pytest.approx(math.radians(2.0))
    np.testing.assert_allclose(w.route("r"), [[0.5, 1.0], [3.5, 1.0]])
    assert w.bounds == ((0.0, 0.0), (4.0, 3.0))


def _error(text: str) -> WorldFileError:
    with pytest.raises(WorldFileError) as e:
        parse_world(text, file="bad.toml")
    return e.value


def test_syntax_error_names_file_and_line():
    e = _error('name = "x"\n[[segments]]\na = [0, 0\nb = [1, 0]\n')
    assert e.file == "bad.toml" and e.line in (3, 4)
    assert str(e).startswith("bad.toml, line ")
    assert "TOML syntax error" in str(e)
    e = _error('name = "x"\n[[segments]]\na = [0, 0\n')
    assert e.line == 3 and "end of the file" in e.problem


def test_unknown_material_names_key_path():
    text = GOOD + '[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "glas"\n'
    e = _error(text)
    assert e.key == "segments[1].material"
    assert "unknown material 'glas'" in str(e) and "glass" in str(e)


def test_bad_point_and_missing_key_and_unknown_key():
    e = _error('[[segments]]\na = [0, "x"]\nb = [1, 1]\nmaterial = "wall"\n')
    assert e.key == "segments[0].a" and "[x, y]" in e.problem
    e = _error('[[segments]]\na = [0, 0]\nmaterial = "wall"\n')
    assert e.key == "segments[0].b" and "missing" in e.problem
    e = _error('[[boxes]]\ncentre = [0, 0]\nsize = [1, 1]\nmaterial = "wall"\n')
    assert e.key == "boxes[0].centre" and "unknown key" in e.problem


def test_bad_material_values():
    e = _error('[materials.x]\nkind = "glas"\n[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "x"\n')
    assert e.key == "materials.x.kind"
    e = _error('[materials.x]\nkind = "glass"\ntransmission = 1.5\n[[segments]]\na = [0, 0]\nb = [1, 1]\n'
               'material = "x"\n')
    assert e.key == "materials.x.transmission" and "between 0 and 1" in e.problem


def test_zero_length_segment_and_bad_route():
    e = _error('[[segments]]\na = [1, 1]\nb = [1, 1]\nmaterial = "wall"\n')
    assert e.key == "segments[0]" and "zero length" in e.problem
    e = _error('[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "wall"\n[routes.r]\nwaypoints = [[0, 0]]\n')
    assert e.key == "routes.r.waypoints"
    e = _error('default_route = "nope"\n[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "wall"\n')
    assert e.key == "default_route"


def test_file_errors(tmp_path: Path):
    p = tmp_path / "w.toml"
    p.write_text('[[segments]]\na = [0, 0]\nb = [1, 1]\nmaterial = "wood"\n')
    with pytest.raises(WorldFileError, match=r"w\.toml, key segments\[0\]\.material: unknown material 'wood'"):
        load_world(str(p))
    with pytest.raises(WorldFileError, match="cannot read"):
        load_world(str(tmp_path / "missing.toml"))
    with pytest.raises(WorldFileError, match="no built-in world named 'ofice'"):
        load_world("ofice")
    assert isinstance(WorldFileError("f", "p"), ValueError)


def test_world_errors_survive_a_process_pool():
    """A worker that meets a bad world reports the error itself (a WorldFileError that could not be unpickled
    broke the whole pool instead)."""
    import pickle

    e = pickle.loads(pickle.dumps(WorldFileError("w.toml", "bad", line=3, key="segments[0]")))
    assert (e.file, e.problem, e.line, e.key, str(e)) == ("w.toml", "bad", 3, "segments[0]",
                                                         "w.toml, line 3, key segments[0]: bad")
    with pytest.raises(RouteError, match=r"world 'office' has no route 'nope'; routes: \['main', 'short'\]"):
        load_world("office").route("nope")
