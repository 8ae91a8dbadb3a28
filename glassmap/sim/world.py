"""Simulated worlds: 2D line segments with materials, loaded from TOML world files.

Frame: ``map``; units metres (angles in the file are in degrees, ``*_deg`` keys, and radians in memory).
The file format is documented in docs/simulator.md. Built-in worlds live in ``glassmap/worlds/*.toml``.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from glassmap.sim.materials import (
    BUILTIN_MATERIALS,
    KIND_BY_NAME,
    KIND_DEFAULTS,
    Material,
    MaterialKind,
)


class WorldFileError(ValueError):
    """A world file could not be read. Carries the file, the line (TOML syntax errors) or the key path
    (e.g. ``segments[3].material``) and the problem."""

    def __init__(self, file: str, problem: str, *, line: int | None = None, key: str | None = None) -> None:
        self.file = file
        self.problem = problem
        self.line = line
        self.key = key
        where = file
        if line is not None:
            where += f", line {line}"
        if key is not None:
            where += f", key {key}"
        super().__init__(f"{where}: {problem}")

    def __reduce__(self):  # keyword fields: picklable, so that a worker process can report it
        return _world_file_error, (self.file, self.problem, self.line, self.key)


def _world_file_error(file: str, problem: str, line: int | None, key: str | None) -> WorldFileError:
    return WorldFileError(file, problem, line=line, key=key)


class RouteError(ValueError):
    """A world has no route of the name asked for."""


@dataclass
class World:
    """A 2D world in the map frame (metres).

    segments: (m, 2, 2) float64, ``segments[i, 0]`` and ``segments[i, 1]`` are the end points (x, y).
    segment_material: (m,) int index into ``materials``. segment_kind: (m,) int ``MaterialKind`` code.
    segment_source: (m,) key path of the file element each segment came from (for messages).
    routes: name -> (k, 2) waypoints (metres); ``default_route`` names the one used when none is given.
    start_pose: (3,) x, y (m), yaw (rad) where the robot starts.
    laser: overrides of ``glassmap.sim.laser.LaserParams`` fields for this world (the ``[laser]`` table;
        angles in rad), applied by ``glassmap.sim.laser.world_laser_params``.
    """

    name: str
    segments: np.ndarray
    segment_material: np.ndarray
    materials: list[Material]
    routes: dict[str, np.ndarray]
    start_pose: np.ndarray
    default_route: str | None = None
    description: str = ""
    path: str | None = None
    segment_source: list[str] = field(default_factory=list)
    laser: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.segments = np.asarray(self.segments, dtype=np.float64).reshape(-1, 2, 2)
        self.segment_material = np.asarray(self.segment_material, dtype=np.int64)
        self.start_pose = np.asarray(self.start_pose, dtype=np.float64)
        kinds = np.array([int(m.kind) for m in self.materials], dtype=np.int64)
        self.segment_kind = kinds[self.segment_material] if len(self.segment_material) else np.zeros(0, np.int64)

    @property
    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((xmin, ymin), (xmax, ymax)) of all segments (m, map frame)."""
        pts = self.segments.reshape(-1, 2)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1]))

    @property
    def segment_is_glass(self) -> np.ndarray:
        """(m,) bool: the segment is a glass pane."""
        return self.segment_kind == int(MaterialKind.GLASS)

    def material_named(self, name: str) -> Material:
        for m in self.materials:
            if m.name == name:
                return m
        raise KeyError(name)

    def route(self, name: str | None = None) -> np.ndarray:
        """Waypoints (k, 2) of route ``name`` (default: the world's default route)."""
        if name is None:
            name = self.default_route
        if name is None or name not in self.routes:
            raise RouteError(f"world {self.name!r} has no route {name!r}; routes: {sorted(self.routes)}")
        return self.routes[name]

    def route_clearance(self, name: str | None = None) -> float:
        """Smallest distance (m) between the route polyline and any segment of the world."""
        return polyline_clearance(self.route(name), self.segments)


def polyline_clearance(points: np.ndarray, segments: np.ndarray) -> float:
    """Smallest distance (m) between a polyline (k, 2) and segments (m, 2, 2)."""
    pts = np.asarray(points, dtype=np.float64)
    legs = np.stack([pts[:-1], pts[1:]], axis=1)
    return float(segment_distances(legs, segments).min())


def segment_distances(s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """Pairwise distances (m) between segments s1 (p, 2, 2) and s2 (q, 2, 2); returns (p, q)."""

    def point_seg(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        ab = b - a
        ap = p - a
        denom = np.maximum((ab * ab).sum(-1), 1e-18)
        t = np.clip((ap * ab).sum(-1) / denom, 0.0, 1.0)
        return np.linalg.norm(ap - t[..., None] * ab, axis=-1)

    a1, b1 = s1[:, None, 0], s1[:, None, 1]
    a2, b2 = s2[None, :, 0], s2[None, :, 1]
    d = np.minimum.reduce([point_seg(a1, a2, b2), point_seg(b1, a2, b2), point_seg(a2, a1, b1),
                           point_seg(b2, a1, b1)])

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    d1, d2 = b1 - a1, b2 - a2
    o1 = cross(d1, a2 - a1) * cross(d1, b2 - a1)
    o2 = cross(d2, a1 - a2) * cross(d2, b1 - a2)
    return np.where((o1 < 0) & (o2 < 0), 0.0, d)


# ----------------------------------------------------------------------------------------------------------
# Loading

BUILTIN_DIR = "worlds"


def builtin_worlds() -> list[str]:
    """Names of the worlds shipped with the package."""
    root = resources.files("glassmap") / BUILTIN_DIR
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def load_world(name_or_path: str | Path) -> World:
    """Load a built-in world by name (``office``, ``glass-corridor``, ``room``, ``lobby``) or a TOML file.

    Raises WorldFileError naming the file, the line or key path, and the problem.
    """
    s = str(name_or_path)
    if not s.endswith(".toml") and "/" not in s and "\\" not in s:
        res = resources.files("glassmap") / BUILTIN_DIR / f"{s}.toml"
        if not res.is_file():
            raise WorldFileError(s, f"no built-in world named {s!r}; built-in worlds: {builtin_worlds()} "
                                    f"(or give a path to a .toml file)")
        return parse_world(res.read_text(encoding="utf-8"), file=f"<built-in {s}.toml>", default_name=s)
    path = Path(s)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise WorldFileError(s, f"cannot read the world file: {e.strerror or e}") from e
    return parse_world(text, file=s, default_name=path.stem)


def parse_world(text: str, file: str = "<string>", default_name: str = "world") -> World:
    """Parse the text of a TOML world file (see docs/simulator.md)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = re.search(r"\(at line (\d+), column (\d+)\)", msg)
        line = int(m.group(1)) if m else None
        if m is None and "(at end of document)" in msg:
            line = len(text.splitlines()) or 1
        problem = re.sub(r"\s*\(at (line \d+, column \d+|end of document)\)", "", msg)
        if line is not None and m is None:
            problem += " (at the end of the file)"
        if m:
            problem += f" (column {m.group(2)})"
        raise WorldFileError(file, f"TOML syntax error: {problem}", line=line) from e
    return _Builder(file).build(doc, default_name)


_TOP_KEYS = {"name", "description", "start", "default_route", "materials", "segments", "polylines", "boxes",
             "panes", "circles", "routes", "laser"}
# [laser] keys: LaserParams fields (the *_deg keys are given in degrees and stored in radians)
LASER_KEYS = {"intensity_scale", "reference_range", "near_range", "range_exponent", "cos_exponent",
              "intensity_noise", "saturation", "detection_threshold", "range_noise", "range_noise_slope",
              "dropout_prob", "min_reading", "max_reading", "glass_window_deg", "glass_window_ref_range",
              "glass_window_exponent", "glass_window_min_deg", "glass_return_prob", "glass_fresnel_r0"}
_MATERIAL_KEYS = {"kind", "rho", "cos_exponent", "specular_gain", "lobe_width_deg", "no_return_prob",
                  "transmission", "surface_rho", "mirror_reflectance"}


class _Builder:
    def __init__(self, file: str) -> None:
        self.file = file
        self.segs: list[tuple[float, float, float, float]] = []
        self.mats: list[int] = []
        self.src: list[str] = []

    # -- helpers -------------------------------------------------------------------------------------------
    def err(self, key: str, problem: str) -> WorldFileError:
        return WorldFileError(self.file, problem, key=key)

    def table(self, value: Any, key: str, allowed: set[str]) -> dict:
        if not isinstance(value, dict):
            raise self.err(key, f"must be a table, got {type(value).__name__}")
        unknown = sorted(set(value) - allowed)
        if unknown:
            raise self.err(f"{key}.{unknown[0]}", f"unknown key; allowed keys: {sorted(allowed)}")
        return value

    def number(self, tbl: dict, name: str, key: str, default: float | None = None, *, positive: bool = False,
               nonneg: bool = False) -> float:
        if name not in tbl:
            if default is None:
                raise self.err(f"{key}.{name}", "missing (a number is required)")
            return default
        v = tbl[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(f"{key}.{name}", f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.err(f"{key}.{name}", f"must be > 0, got {v!r}")
        if nonneg and v < 0:
            raise self.err(f"{key}.{name}", f"must be >= 0, got {v!r}")
        return float(v)

    def point(self, tbl: dict, name: str, key: str) -> np.ndarray:
        if name not in tbl:
            raise self.err(f"{key}.{name}", "missing (a point [x, y] in metres is required)")
        return self.point_value(tbl[name], f"{key}.{name}")

    def point_value(self, v: Any, key: str) -> np.ndarray:
        if (not isinstance(v, list) or len(v) != 2
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c)
                           for c in v)):
            raise self.err(key, f"must be a point [x, y] of two finite numbers (metres), got {v!r}")
        return np.array(v, dtype=np.float64)

    def points(self, tbl: dict, name: str, key: str, min_len: int) -> np.ndarray:
        if name not in tbl:
            raise self.err(f"{key}.{name}", f"missing (a list of at least {min_len} points [x, y])")
        v = tbl[name]
        if not isinstance(v, list) or len(v) < min_len:
            raise self.err(f"{key}.{name}", f"must be a list of at least {min_len} points [x, y]")
        return np.array([self.point_value(p, f"{key}.{name}[{i}]") for i, p in enumerate(v)])

    def elements(self, doc: dict, name: str) -> list:
        v = doc.get(name, [])
        if not isinstance(v, list):
            raise self.err(name, f"must be an array of tables ([[{name}]]), got {type(v).__name__}")
        return v

    def material_ref(self, tbl: dict, name: str, key: str, default: str | None = None) -> int:
        if name not in tbl and default is not None:
            v = default
        elif name not in tbl:
            raise self.err(f"{key}.{name}", f"missing; known materials: {sorted(self.mat_index)}")
        else:
            v = tbl[name]
        if not isinstance(v, str) or v not in self.mat_index:
            raise self.err(f"{key}.{name}", f"unknown material {v!r}; known materials: {sorted(self.mat_index)}")
        return self.mat_index[v]

    def add(self, a: np.ndarray, b: np.ndarray, mat: int, key: str) -> None:
        if float(np.hypot(*(b - a))) < 1e-6:
            raise self.err(key, f"segment has zero length (from {a.tolist()} to {b.tolist()})")
        self.segs.append((a[0], a[1], b[0], b[1]))
        self.mats.append(mat)
        self.src.append(key)

    def add_polygon(self, pts: np.ndarray, mat: int, key: str) -> None:
        for i in range(len(pts)):
            self.add(pts[i], pts[(i + 1) % len(pts)], mat, key)

    # -- sections ------------------------------------------------------------------------------------------
    def build(self, doc: dict, default_name: str) -> World:
        unknown = sorted(set(doc) - _TOP_KEYS)
        if unknown:
            raise self.err(unknown[0], f"unknown top-level key; allowed: {sorted(_TOP_KEYS)}")
        name = doc.get("name", default_name)
        if not isinstance(name, str) or not name:
            raise self.err("name", "must be a non-empty string")
        description = doc.get("description", "")
        if not isinstance(description, str):
            raise self.err("description", "must be a string")
        self.build_materials(doc.get("materials", {}))
        for i, s in enumerate(self.elements(doc, "segments")):
            k = f"segments[{i}]"
            s = self.table(s, k, {"a", "b", "material"})
            self.add(self.point(s, "a", k), self.point(s, "b", k), self.material_ref(s, "material", k), k)
        for i, s in enumerate(self.elements(doc, "polylines")):
            k = f"polylines[{i}]"
            s = self.table(s, k, {"points", "material", "closed"})
            pts = self.points(s, "points", k, 2)
            closed = s.get("closed", False)
            if not isinstance(closed, bool):
                raise self.err(f"{k}.closed", f"must be true or false, got {closed!r}")
            mat = self.material_ref(s, "material", k)
            for j in range(len(pts) - 1):
                self.add(pts[j], pts[j + 1], mat, f"{k}.points[{j}]")
            if closed:
                self.add(pts[-1], pts[0], mat, f"{k}.points[{len(pts) - 1}]")
        for i, s in enumerate(self.elements(doc, "boxes")):
            self.build_box(s, f"boxes[{i}]")
        for i, s in enumerate(self.elements(doc, "circles")):
            self.build_circle(s, f"circles[{i}]")
        for i, s in enumerate(self.elements(doc, "panes")):
            self.build_panes(s, f"panes[{i}]")
        if not self.segs:
            raise self.err("segments", "the world has no segments")
        start = self.table(doc.get("start", {}), "start", {"x", "y", "yaw_deg"})
        start_pose = np.array([self.number(start, "x", "start", 0.0), self.number(start, "y", "start", 0.0),
                               math.radians(self.number(start, "yaw_deg", "start", 0.0))])
        routes = self.build_routes(doc.get("routes", {}))
        default_route = doc.get("default_route", next(iter(routes), None))
        if default_route is not None and default_route not in routes:
            raise self.err("default_route", f"names no route; routes: {sorted(routes)}")
        if "start" not in doc and default_route is not None:
            wp = routes[default_route]
            start_pose = np.array([wp[0, 0], wp[0, 1], math.atan2(*(wp[1] - wp[0])[::-1])])
        return World(name=name, segments=np.array(self.segs, dtype=np.float64).reshape(-1, 2, 2),
                     segment_material=np.array(self.mats, dtype=np.int64), materials=self.materials,
                     routes=routes, start_pose=start_pose, default_route=default_route,
                     description=description, path=self.file, segment_source=self.src,
                     laser=self.build_laser(doc.get("laser", {})))

    def build_laser(self, tbl: Any) -> dict[str, float]:
        tbl = self.table(tbl, "laser", LASER_KEYS)
        out = {}
        for name in tbl:
            v = self.number(tbl, name, "laser", nonneg=True)
            if name.endswith("_deg"):
                out[name[:-4]] = math.radians(v)
            else:
                out[name] = v
        for f in ("dropout_prob", "glass_return_prob", "glass_fresnel_r0"):
            if not 0 <= out.get(f, 0.0) <= 1:
                raise self.err(f"laser.{f}", f"must be between 0 and 1, got {out[f]!r}")
        return out

    def build_materials(self, mats: Any) -> None:
        table = dict(BUILTIN_MATERIALS)
        mats = self.table(mats, "materials", set(mats) if isinstance(mats, dict) else set())
        for name, spec in mats.items():
            k = f"materials.{name}"
            spec = self.table(spec, k, _MATERIAL_KEYS)
            kind_name = spec.get("kind", table[name].kind.name.lower() if name in table else None)
            if kind_name is None:
                raise self.err(f"{k}.kind", f"missing; one of {sorted(KIND_BY_NAME)}")
            if not isinstance(kind_name, str) or kind_name.lower() not in KIND_BY_NAME:
                raise self.err(f"{k}.kind", f"unknown kind {kind_name!r}; one of {sorted(KIND_BY_NAME)}")
            kind = KIND_BY_NAME[kind_name.lower()]
            params: dict[str, Any] = dict(KIND_DEFAULTS[kind])
            for f in ("rho", "specular_gain", "no_return_prob", "transmission", "surface_rho", "cos_exponent",
                      "mirror_reflectance"):
                if f in spec:
                    params[f] = self.number(spec, f, k, nonneg=True)
            if "lobe_width_deg" in spec:
                params["lobe_width"] = math.radians(self.number(spec, "lobe_width_deg", k, positive=True))
            for f in ("no_return_prob", "transmission", "mirror_reflectance"):
                if not 0 <= params.get(f, 0.0) <= 1:
                    raise self.err(f"{k}.{f}", f"must be between 0 and 1, got {params[f]!r}")
            table[name] = Material(name=name, kind=kind, **params)
        self.materials = list(table.values())
        self.mat_index = {m.name: i for i, m in enumerate(self.materials)}

    def build_box(self, s: Any, k: str) -> None:
        s = self.table(s, k, {"center", "size", "yaw_deg", "material"})
        c = self.point(s, "center", k)
        size = self.point(s, "size", k)
        if (size <= 0).any():
            raise self.err(f"{k}.size", f"must be [width, depth] > 0 (metres), got {size.tolist()}")
        yaw = math.radians(self.number(s, "yaw_deg", k, 0.0))
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * size / 2
        self.add_polygon(c + corners @ rot.T, self.material_ref(s, "material", k), k)

    def build_circle(self, s: Any, k: str) -> None:
        s = self.table(s, k, {"center", "radius", "sides", "material"})
        c = self.point(s, "center", k)
        r = self.number(s, "radius", k, positive=True)
        n = int(self.number(s, "sides", k, 16.0))
        if n < 3:
            raise self.err(f"{k}.sides", f"must be >= 3, got {n}")
        ang = np.arange(n) * 2 * math.pi / n
        self.add_polygon(c + r * np.stack([np.cos(ang), np.sin(ang)], axis=1), self.material_ref(s, "material", k), k)

    def build_panes(self, s: Any, k: str) -> None:
        """A straight glass wall from a to b split into panes with frames (mullions) at both ends and between.

        Keys: a, b (m), pane_width (approximate width of one pane, m), frame_width (m, along the wall),
        frame_depth (m, across; 0 = a flat frame segment in the wall line), material, frame_material.
        """
        s = self.table(s, k, {"a", "b", "pane_width", "frame_width", "frame_depth", "material", "frame_material"})
        a, b = self.point(s, "a", k), self.point(s, "b", k)
        length = float(np.hypot(*(b - a)))
        pane_w = self.number(s, "pane_width", k, 1.5, positive=True)
        fw = self.number(s, "frame_width", k, 0.06, nonneg=True)
        fd = self.number(s, "frame_depth", k, 0.08, nonneg=True)
        glass = self.material_ref(s, "material", k, "glass")
        frame = self.material_ref(s, "frame_material", k, "frame")
        n = max(1, round(length / pane_w))
        if length <= (n + 1) * fw + 1e-3:
            raise self.err(k, f"wall of {length:.2f} m is too short for {n} panes with {fw} m frames")
        u = (b - a) / length
        nrm = np.array([-u[1], u[0]])
        glass_len = (length - (n + 1) * fw) / n
        pos = 0.0
        for i in range(n + 1):
            if fw > 0:
                f0, f1 = a + u * pos, a + u * (pos + fw)
                if fd > 0:
                    self.add_polygon(np.array([f0 - nrm * fd / 2, f1 - nrm * fd / 2, f1 + nrm * fd / 2,
                                               f0 + nrm * fd / 2]), frame, f"{k}.frame[{i}]")
                else:
                    self.add(f0, f1, frame, f"{k}.frame[{i}]")
            pos += fw
            if i < n:
                self.add(a + u * pos, a + u * (pos + glass_len), glass, f"{k}.pane[{i}]")
                pos += glass_len

    def build_routes(self, routes: Any) -> dict[str, np.ndarray]:
        routes = self.table(routes, "routes", set(routes) if isinstance(routes, dict) else set())
        out = {}
        for name, spec in routes.items():
            k = f"routes.{name}"
            spec = self.table(spec, k, {"waypoints"})
            out[name] = self.points(spec, "waypoints", k, 2)
        return out


def default_material_list() -> list[Material]:
    """The built-in materials (wall first), e.g. for building a ``World`` in code."""
    return list(BUILTIN_MATERIALS.values())
