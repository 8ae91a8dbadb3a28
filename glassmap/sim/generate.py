"""Generated worlds: random buildings in the TOML world format, deterministic per seed.

A world is built around a closed route polygon (the robot's loop, 60-200 m): a corridor or hall of
half-width ``hw`` follows it, its two walls are the polygon offset by +-hw, rooms of depth 3-6 m lie
behind them (partitions, furniture), and each wall is split into sections of plain wall, glass panes with
mullions, glass doors in metal or wooden frames, polished metal and whiteboards. Kinds:

* ``office``: an irregular convex polygon (4-7 corners, any angle), corridor 1.8-2.8 m, glass offices;
* ``corridor``: a long rectangle-like loop of narrow corridors (long featureless stretches);
* ``lobby``: a wide hall (5-8 m) with a glass facade, pillars and furniture in the hall;
* ``atrium``: a facetted ring (8-16 sides) round a glass atrium, 4-6 m wide.

Everything is rotated by a random angle (no Manhattan layout). Per-world laser parameters ([laser]) and
material parameters are drawn from the ranges in ``LASER_RANGES`` / ``MATERIAL_RANGES``
(docs/simulator.md). Every route keeps at least ``MIN_CLEARANCE`` from every segment (checked).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

KINDS = ("office", "corridor", "lobby", "atrium")
MIN_CLEARANCE = 0.4  # m, route to any segment
LOOP_LENGTH = (60.0, 200.0)  # m, the main loop's length

# per-world laser parameters: uniform in [lo, hi] (the *_deg keys in degrees)
LASER_RANGES: dict[str, tuple[float, float]] = {
    "intensity_scale": (4500.0, 7500.0),
    "intensity_noise": (0.08, 0.20),
    "range_exponent": (0.9, 1.2),
    "cos_exponent": (0.8, 1.4),
    "detection_threshold": (40.0, 90.0),
    "range_noise": (0.008, 0.016),
    "glass_window_deg": (10.0, 20.0),
    "glass_window_exponent": (0.5, 0.9),
    "glass_return_prob": (0.6, 0.95),
    "glass_fresnel_r0": (0.03, 0.06),
}
# per-world material parameters: material -> field -> (lo, hi)
MATERIAL_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "wall": {"rho": (0.4, 0.85)},
    "glass": {"transmission": (0.75, 0.95), "specular_gain": (20.0, 60.0), "lobe_width_deg": (0.2, 0.5),
              "surface_rho": (0.06, 0.2)},
    "tinted_glass": {"transmission": (0.55, 0.8), "specular_gain": (20.0, 60.0), "lobe_width_deg": (0.2, 0.5),
                     "surface_rho": (0.1, 0.25)},
    "metal": {"rho": (0.15, 0.35), "specular_gain": (4.0, 12.0), "lobe_width_deg": (1.5, 4.0),
              "mirror_reflectance": (0.3, 0.7)},
    "whiteboard": {"rho": (0.7, 0.9), "specular_gain": (1.5, 4.0), "lobe_width_deg": (3.0, 6.0)},
    "dark": {"rho": (0.03, 0.1), "no_return_prob": (0.05, 0.3)},
    "object": {"rho": (0.3, 0.6)},
}
_KIND_OF = {"tinted_glass": "glass"}


class GeneratorError(RuntimeError):
    """The generator could not build a valid world for this seed (a bug: every seed should work)."""


@dataclass
class GeneratedWorld:
    """A generated world: its TOML text and what it was drawn from."""

    seed: int
    kind: str
    text: str
    loop_length: float  # m
    clearance: float  # m, smallest route-to-segment distance

    def save(self, path: str | Path) -> Path:
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.text, encoding="utf-8")
        return p


# ---------------------------------------------------------------------------------------------------------
# geometry

def _offset(poly: np.ndarray, d: float) -> np.ndarray | None:
    """A convex counter-clockwise polygon offset by d (m, > 0 outwards); None if it degenerates."""
    n = len(poly)
    e = np.roll(poly, -1, axis=0) - poly
    u = e / np.hypot(e[:, 0], e[:, 1])[:, None]
    nrm = np.stack([u[:, 1], -u[:, 0]], axis=1)  # outward normal of a CCW polygon
    p0 = poly + d * nrm
    out = np.empty_like(poly)
    for i in range(n):  # vertex i: lines of edges i - 1 and i
        a, da = p0[i - 1], u[i - 1]
        b, db = p0[i], u[i]
        den = da[0] * db[1] - da[1] * db[0]
        if abs(den) < 1e-9:
            out[i] = b
            continue
        s = ((b[0] - a[0]) * db[1] - (b[1] - a[1]) * db[0]) / den
        out[i] = a + s * da
    e2 = np.roll(out, -1, axis=0) - out
    if (np.einsum("ij,ij->i", e2, e) <= 0).any() or (np.hypot(e2[:, 0], e2[:, 1]) < 0.5).any():
        return None
    return out


def _perimeter(poly: np.ndarray) -> float:
    e = np.roll(poly, -1, axis=0) - poly
    return float(np.hypot(e[:, 0], e[:, 1]).sum())


def _ellipse_polygon(rng: np.random.Generator, n: int, a: float, b: float, min_gap_deg: float) -> np.ndarray:
    for _ in range(200):
        ang = np.sort(rng.uniform(0, 2 * math.pi, n))
        gaps = np.diff(np.r_[ang, ang[0] + 2 * math.pi])
        if gaps.min() >= math.radians(min_gap_deg):
            return np.stack([a * np.cos(ang), b * np.sin(ang)], axis=1)
    ang = np.arange(n) * 2 * math.pi / n
    return np.stack([a * np.cos(ang), b * np.sin(ang)], axis=1)


def _route_polygon(kind: str, rng: np.random.Generator) -> np.ndarray:
    if kind == "corridor":
        length, width = rng.uniform(25, 75), rng.uniform(6, 14)
        c = rng.uniform(1.0, 3.0)  # chamfered corners
        x, y = length / 2, width / 2
        poly = np.array([[-x + c, -y], [x - c, -y], [x, -y + c], [x, y - c], [x - c, y], [-x + c, y], [-x, y - c],
                         [-x, -y + c]])
    elif kind == "atrium":
        n = int(rng.integers(8, 17))
        r = rng.uniform(11, 22)
        ang = np.arange(n) * 2 * math.pi / n + rng.uniform(0, math.pi)
        sx = rng.uniform(0.8, 1.0)
        poly = np.stack([r * np.cos(ang), sx * r * np.sin(ang)], axis=1)
    elif kind == "lobby":
        poly = _ellipse_polygon(rng, int(rng.integers(4, 6)), rng.uniform(13, 22), rng.uniform(10, 15), 50)
    else:
        poly = _ellipse_polygon(rng, int(rng.integers(4, 8)), rng.uniform(12, 28), rng.uniform(7, 14), 35)
    per = _perimeter(poly)
    lo, hi = LOOP_LENGTH
    if per < lo + 5 or per > hi - 5:
        poly = poly * (np.clip(per, lo + 5, hi - 5) / per)
    return poly


# ---------------------------------------------------------------------------------------------------------
# the builder

class _Builder:
    def __init__(self, rng: np.random.Generator, rot: float, shift: np.ndarray) -> None:
        self.rng = rng
        self.c, self.s = math.cos(rot), math.sin(rot)
        self.shift = shift
        self.blocks: list[str] = []
        self.rot_deg = math.degrees(rot)

    def xy(self, p) -> str:
        x = self.c * p[0] - self.s * p[1] + self.shift[0]
        y = self.s * p[0] + self.c * p[1] + self.shift[1]
        return f"[{x:.3f}, {y:.3f}]"

    def segment(self, a, b, material: str) -> None:
        if math.hypot(b[0] - a[0], b[1] - a[1]) < 0.01:  # slivers left over by the section split
            return
        self.blocks.append(f'[[segments]]\na = {self.xy(a)}\nb = {self.xy(b)}\nmaterial = "{material}"\n')

    def polyline(self, pts, material: str, closed: bool = False) -> None:
        pts_s = ", ".join(self.xy(p) for p in pts)
        self.blocks.append(f'[[polylines]]\npoints = [{pts_s}]\nmaterial = "{material}"\n'
                           f'closed = {"true" if closed else "false"}\n')

    def panes(self, a, b, pane_width: float, material: str = "glass", frame_material: str = "frame",
              frame_width: float = 0.06, frame_depth: float = 0.08) -> None:
        self.blocks.append(f'[[panes]]\na = {self.xy(a)}\nb = {self.xy(b)}\npane_width = {pane_width:.3f}\n'
                           f'frame_width = {frame_width:.3f}\nframe_depth = {frame_depth:.3f}\n'
                           f'material = "{material}"\nframe_material = "{frame_material}"\n')

    def box(self, center, size, yaw: float, material: str) -> None:
        self.blocks.append(f'[[boxes]]\ncenter = {self.xy(center)}\nsize = [{size[0]:.3f}, {size[1]:.3f}]\n'
                           f'yaw_deg = {math.degrees(yaw) + self.rot_deg:.2f}\nmaterial = "{material}"\n')

    def circle(self, center, radius: float, sides: int, material: str) -> None:
        self.blocks.append(f'[[circles]]\ncenter = {self.xy(center)}\nradius = {radius:.3f}\nsides = {sides}\n'
                           f'material = "{material}"\n')


_SECTION_WEIGHTS = {
    # kind: (wall, glass, door, metal, whiteboard, tinted glass)
    "office": (0.30, 0.40, 0.10, 0.06, 0.08, 0.06),
    "corridor": (0.62, 0.18, 0.06, 0.05, 0.06, 0.03),
    "lobby": (0.25, 0.45, 0.08, 0.07, 0.05, 0.10),
    "atrium": (0.25, 0.45, 0.08, 0.07, 0.05, 0.10),
}
_SECTIONS = ("wall", "glass", "door", "metal", "whiteboard", "tinted")


def _wall_edge(b: _Builder, a: np.ndarray, c: np.ndarray, inward: np.ndarray, kind: str, depth: float,
               all_glass: bool = False) -> None:
    """One straight wall from a to c split into sections; ``inward`` points into the corridor; rooms of
    ``depth`` m lie on the other side (furniture, partitions)."""
    rng = b.rng
    length = float(np.hypot(*(c - a)))
    u = (c - a) / length
    back = -inward
    pos = 0.0
    margin = min(0.5, length / 4)
    b.segment(a, a + u * margin, "wall")
    pos = margin
    weights = np.array(_SECTION_WEIGHTS[kind])
    while pos < length - margin - 1e-6:
        sec = rng.uniform(2.5, 8.0)
        kind_s = "glass" if all_glass else _SECTIONS[rng.choice(len(_SECTIONS), p=weights / weights.sum())]
        if kind_s == "door":
            sec = rng.uniform(1.0, 2.2)
        sec = min(sec, length - margin - pos)
        if sec < 1.0:
            b.segment(a + u * pos, c - u * margin, "wall")
            pos = length - margin
            break
        p0, p1 = a + u * pos, a + u * (pos + sec)
        if kind_s in ("glass", "tinted") and sec >= 1.2:
            mat = "tinted_glass" if kind_s == "tinted" else "glass"
            b.panes(p0, p1, rng.uniform(1.1, 1.8), material=mat, frame_depth=float(rng.choice([0.0, 0.06, 0.08])))
        elif kind_s == "door" and sec >= 1.0:
            b.panes(p0, p1, sec / (1 + int(sec > 1.6)), material="glass",
                    frame_material=str(rng.choice(["metal", "frame"])), frame_width=0.08, frame_depth=0.06)
        elif kind_s == "metal":
            b.segment(p0, p1, "metal")
        else:
            b.segment(p0, p1, "wall")
            if kind_s == "whiteboard" and sec > 1.5:
                w0 = pos + rng.uniform(0.2, 0.5)
                w1 = min(pos + sec - 0.2, w0 + rng.uniform(1.0, 2.5))
                b.segment(a + u * w0 + inward * 0.02, a + u * w1 + inward * 0.02, "whiteboard")
            elif rng.random() < 0.15:  # retroreflective tape on the wall
                w0 = pos + rng.uniform(0.2, sec - 0.4)
                b.segment(a + u * w0 + inward * 0.01, a + u * (w0 + 0.2) + inward * 0.01, "retro")
        # furniture in the room behind (seen through glass)
        if rng.random() < 0.8 and depth > 2.0:
            for _ in range(int(rng.integers(1, 4))):
                cpos = p0 + u * rng.uniform(0.5, max(0.6, sec - 0.5)) + back * rng.uniform(0.8, depth - 0.8)
                size = (rng.uniform(0.4, 1.8), rng.uniform(0.4, 0.9))
                mat = str(rng.choice(["object", "object", "dark", "metal"], p=[0.45, 0.15, 0.3, 0.1]))
                b.box(cpos, size, float(math.atan2(u[1], u[0]) + rng.normal(0, 0.3)), mat)
        pos += sec
        # partition between rooms at this section boundary
        if depth > 2.0 and depth < pos < length - depth and rng.random() < 0.5:
            q = a + u * pos
            if rng.random() < 0.3:
                b.panes(q, q + back * depth, rng.uniform(1.2, 1.8), frame_depth=0.06)
            else:
                b.segment(q, q + back * depth, "wall")
    if pos < length:
        b.segment(a + u * pos, c, "wall")


def _place_clutter(b: _Builder, route: np.ndarray, n: int, hw: float, pillars: bool) -> None:
    """Pillars and furniture in the hall / corridor, only where they keep the route's clearance."""
    rng = b.rng
    legs = np.diff(np.vstack([route, route[:1]]), axis=0)
    lens = np.hypot(legs[:, 0], legs[:, 1])
    for _ in range(n):
        i = int(rng.choice(len(legs), p=lens / lens.sum()))
        u = legs[i] / lens[i]
        nrm = np.array([u[1], -u[0]])
        side = rng.choice([-1.0, 1.0])
        along = route[i] + u * rng.uniform(0.15, 0.85) * lens[i]
        if pillars and rng.random() < 0.5:
            r = rng.uniform(0.15, 0.45)
            off = rng.uniform(r + MIN_CLEARANCE + 0.25, hw - 0.05)
            c = along + side * nrm * off
            if off + r > hw - 0.05:
                continue
            if _point_route_distance(c, route) < r + MIN_CLEARANCE + 0.2:
                continue
            b.circle(c, r, int(rng.integers(8, 17)), str(rng.choice(["wall", "metal", "object"])))
            continue
        w, d = rng.uniform(0.5, 2.0), rng.uniform(0.4, 0.9)
        off = hw - d / 2 - rng.uniform(0.02, 0.2)
        if off - math.hypot(w, d) / 2 < MIN_CLEARANCE + 0.2:
            continue
        c = along + side * nrm * off
        if _point_route_distance(c, route) < math.hypot(w, d) / 2 + MIN_CLEARANCE + 0.15:
            continue
        b.box(c, (w, d), math.atan2(u[1], u[0]), str(rng.choice(["object", "dark", "metal", "whiteboard"],
                                                                 p=[0.4, 0.35, 0.15, 0.1])))


def _point_route_distance(p: np.ndarray, route: np.ndarray) -> float:
    a = route
    bb = np.roll(route, -1, axis=0)
    ab = bb - a
    t = np.clip(((p - a) * ab).sum(1) / (ab * ab).sum(1), 0, 1)
    return float(np.hypot(*(a + t[:, None] * ab - p).T).min())


def generate_world(seed: int, kind: str | None = None) -> GeneratedWorld:
    """The world of ``seed`` (kind None: ``KINDS[seed % 4]``, so any 4 consecutive seeds give every kind).
    Same seed and kind, same text."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x61A55]))
    k = kind if kind is not None else KINDS[int(seed) % len(KINDS)]
    if k not in KINDS:
        raise ValueError(f"unknown kind {k!r}; kinds: {', '.join(KINDS)}")
    for attempt in range(20):
        try:
            return _generate(int(seed), k, rng)
        except GeneratorError:
            if attempt == 19:
                raise
    raise AssertionError("unreachable")


def _generate(seed: int, kind: str, rng: np.random.Generator) -> GeneratedWorld:
    route = _route_polygon(kind, rng)
    hw = {"office": rng.uniform(0.9, 1.4), "corridor": rng.uniform(0.9, 1.2), "lobby": rng.uniform(2.5, 4.0),
          "atrium": rng.uniform(2.0, 3.0)}[kind]
    depth = rng.uniform(3.0, 6.0)
    rot = rng.uniform(0, math.pi)
    b = _Builder(rng, rot, np.array([0.0, 0.0]))
    outer = _offset(route, hw)
    inner = _offset(route, -hw)
    if outer is None or inner is None:
        raise GeneratorError("corridor walls degenerate")
    boundary = _offset(route, hw + depth)
    core = _offset(route, -(hw + depth))
    n = len(route)
    for poly, is_outer in ((outer, True), (inner, False)):
        e = np.roll(poly, -1, axis=0) - poly
        for i in range(n):
            a, c = poly[i], poly[(i + 1) % n]
            u = e[i] / np.hypot(*e[i])
            outward = np.array([u[1], -u[0]])
            inward = -outward if is_outer else outward  # into the corridor
            room_depth = depth if (is_outer or core is not None) else 0.0
            all_glass = kind == "atrium" and not is_outer  # the atrium's glass balustrade
            if all_glass:
                room_depth = 0.0
            _wall_edge(b, a, c, inward, kind, room_depth, all_glass=all_glass)
    if boundary is not None:
        b.polyline(boundary, "wall", closed=True)
    if core is not None and kind != "atrium":
        b.polyline(core, "wall", closed=True)
    if kind == "atrium":  # things down in the atrium seen through the balustrade
        cen = route.mean(axis=0)
        for _ in range(int(rng.integers(3, 8))):
            p = cen + rng.normal(0, 2.0, 2)
            if _point_inside(p, inner, margin=1.0):
                if rng.random() < 0.5:
                    b.circle(p, rng.uniform(0.3, 0.8), 12, str(rng.choice(["object", "dark"])))
                else:
                    b.box(p, (rng.uniform(0.6, 2.0), rng.uniform(0.5, 1.0)), rng.uniform(0, math.pi), "object")
    n_clutter = {"office": 4, "corridor": 3, "lobby": 14, "atrium": 10}[kind]
    _place_clutter(b, route, n_clutter, hw, pillars=kind in ("lobby", "atrium"))

    # routes: the loop and a short one (the first legs up to about 30 m)
    loop = np.vstack([route, route[:1]])
    lengths = np.hypot(*np.diff(loop, axis=0).T)
    cum = np.cumsum(lengths)
    m = int(np.searchsorted(cum, 30.0)) + 1
    short = loop[: min(m + 1, len(loop))]
    if len(short) < 2:
        short = loop[:2]
    laser = {key: float(rng.uniform(lo, hi)) for key, (lo, hi) in LASER_RANGES.items()}
    mats = {name: {f: float(rng.uniform(lo, hi)) for f, (lo, hi) in fields.items()}
            for name, fields in MATERIAL_RANGES.items()}

    head = [f"# generated by `glassmap sim generate --seed {seed} --kind {kind}` (glassmap.sim.generate)",
            f'name = "gen-{kind}-{seed}"',
            f'description = "generated {kind}, seed {seed}: loop {cum[-1]:.0f} m, corridor {2 * hw:.1f} m wide"',
            'default_route = "loop"', "",
            "[routes.loop]", "waypoints = [" + ", ".join(b.xy(p) for p in loop) + "]", "",
            "[routes.short]", "waypoints = [" + ", ".join(b.xy(p) for p in short) + "]", "",
            "[laser]"]
    for key, v in laser.items():
        head.append(f"{key} = {v:.5g}")
    head.append("")
    for name, fields in mats.items():
        head.append(f"[materials.{name}]")
        head.append(f'kind = "{_KIND_OF.get(name, name)}"')
        for f, v in fields.items():
            head.append(f"{f} = {v:.5g}")
        head.append("")
    text = "\n".join(head) + "\n" + "\n".join(b.blocks)

    from glassmap.sim.world import parse_world

    world = parse_world(text, file=f"<generated seed {seed}>")
    clearance = min(world.route_clearance("loop"), world.route_clearance("short"))
    if clearance < MIN_CLEARANCE:
        raise GeneratorError(f"route clearance {clearance:.2f} m < {MIN_CLEARANCE} m")
    return GeneratedWorld(seed=seed, kind=kind, text=text, loop_length=float(cum[-1]), clearance=clearance)


def _point_inside(p: np.ndarray, poly: np.ndarray, margin: float) -> bool:
    e = np.roll(poly, -1, axis=0) - poly
    u = e / np.hypot(e[:, 0], e[:, 1])[:, None]
    outward = np.stack([u[:, 1], -u[:, 0]], axis=1)
    return bool((((p - poly) * outward).sum(1) < -margin).all())
