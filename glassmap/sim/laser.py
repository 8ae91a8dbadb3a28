"""Laser model: the Hokuyo UTM-30LX-EW in a world of segments, with glass physics.

All beams are cast against all segments at once (numpy, no per-beam loop): each segment is first mapped to
the interval of beam indices it subtends from the laser, then only those (beam, segment) pairs are
intersected exactly. Hits along a beam are sorted by range and resolved in order:

* an opaque surface (anything but glass) ends the beam; it returns if its intensity reaches the detection
  threshold (and it is not a random no-return of dark material);
* a glass pane returns (a) its narrow specular peak near normal incidence, or (b) a weak surface return with
  probability ``glass_return_prob * (1 - (alpha / w(r))^2)`` inside the half-angle window
  ``w(r) = glass_window * (glass_window_ref_range / r)^glass_window_exponent``; otherwise the beam passes
  through, attenuated by ``transmission^2`` (both ways) for whatever is behind.

Intensity of a hit at range r (m) and incidence angle alpha (rad):

    I = K * (r0 / max(r, r_min))^beta * (rho * cos^k(alpha) + specular_gain * exp(-alpha^2 / (2 sigma^2)))
        * attenuation * LogNormal(0, intensity_noise), clipped at ``saturation``

Frames: ``laser_pose`` is the laser in the map frame; ranges along beams of the laser frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from glassmap.sim.materials import NOTHING, MaterialKind
from glassmap.sim.world import World
from glassmap.types import LaserGeometry, Scan

_GLASS = int(MaterialKind.GLASS)


@dataclass(frozen=True)
class LaserParams:
    """Constants of the laser model (see the module docstring for the equations; docs/simulator.md).

    intensity_scale: K, intensity of a rho = 1 diffuse surface at normal incidence at ``reference_range``.
    reference_range: r0 (m) of the distance term. near_range: r_min (m), the distance term is flat below it.
    range_exponent: beta of the distance term (r0 / max(r, r_min))^beta.
    cos_exponent: k of the diffuse cos^k(alpha) term (1 = Lambertian), unless a material overrides it.
    intensity_noise: sigma of the multiplicative log-normal intensity noise.
    saturation: the largest intensity the sensor reports.
    detection_threshold: hits with a (noisy) intensity below it give no return.
    range_noise: standard deviation (m) of the range noise at 0 m; range_noise_slope: added per metre.
    dropout_prob: probability that a beam reads invalid (NaN) regardless of what it hit.
    min_reading: ranges below it read invalid (NaN) (m). max_reading: nothing is reported beyond it (m);
        returns beyond it read +inf (no return). The rated range (30 m) is LaserGeometry.range_max.
    glass_window: half-angle (rad) of glass's weak surface-return window at ``glass_window_ref_range`` (m).
    glass_window_exponent: the window shrinks as (ref / r)^exponent with range r.
    glass_window_min: the window never shrinks below this half-angle (rad).
    glass_return_prob: probability of the weak surface return at normal incidence (falls to 0 at the
        window's edge as 1 - (alpha / w)^2).
    glass_fresnel_r0: reflectance of a glass surface at normal incidence for the angle dependence of the
        transmission (Schlick: R(alpha) = R0 + (1 - R0) (1 - cos alpha)^5; a pane passes
        transmission * (1 - R(alpha)) / (1 - R0) per pass, so glass gets darker to see through at grazing
        incidence). Set to None to make the transmission independent of the angle.
    multi_echo: also compute the last echo (a wall behind a glass pane that returned the first echo).
    """

    intensity_scale: float = 6000.0
    reference_range: float = 1.0
    near_range: float = 0.5
    range_exponent: float = 1.0
    cos_exponent: float = 1.0
    intensity_noise: float = 0.12
    saturation: float = 12000.0
    detection_threshold: float = 60.0
    range_noise: float = 0.01
    range_noise_slope: float = 0.001
    dropout_prob: float = 0.002
    min_reading: float = 0.1
    max_reading: float = 60.0
    glass_window: float = math.radians(15.0)
    glass_window_ref_range: float = 1.0
    glass_window_exponent: float = 0.7
    glass_window_min: float = math.radians(1.5)
    glass_return_prob: float = 0.85
    glass_fresnel_r0: float | None = 0.04
    multi_echo: bool = True


@dataclass
class SimScan:
    """One simulated scan with per-beam ground truth (arrays of shape (n,), laser frame ranges).

    ranges: measured range (m); NaN = invalid reading (dropout, too close), +inf = no return.
    intensities: measured intensity (sensor units), 0 where there is no return.
    true_range: exact distance (m) to the surface the beam returned from; for a beam without return, to the
        opaque surface it ended on (+inf if none within ``max_reading``).
    material: MaterialKind code of that surface (-1 = nothing hit). segment: its segment index (-1 = none).
    incidence: true incidence angle (rad, 0 = along the surface normal) on that surface; NaN if none.
    is_glass: the return (first echo) came from glass. crossed_glass: the beam passed through at least one
        glass pane before that surface (for no-return beams: anywhere along its path).
    echo_ranges, echo_intensities: (n, 2) first and last echo (multi-echo); the last echo is NaN when the
        beam had a single echo. None when multi_echo is off.
    laser_pose: (3,) the laser pose (x, y, yaw) in the map frame used for the scan.
    """

    ranges: np.ndarray
    intensities: np.ndarray
    true_range: np.ndarray
    material: np.ndarray
    incidence: np.ndarray
    is_glass: np.ndarray
    crossed_glass: np.ndarray
    segment: np.ndarray
    laser_pose: np.ndarray
    geometry: LaserGeometry = field(default_factory=LaserGeometry)
    echo_ranges: np.ndarray | None = None
    echo_intensities: np.ndarray | None = None

    def to_scan(self, stamp: float = 0.0, seq: int = 0) -> Scan:
        """The measurement part as a ``glassmap.types.Scan`` (echoes = [first, last] when multi-echo)."""
        return Scan(stamp=stamp, ranges=self.ranges.copy(), intensities=self.intensities.copy(),
                    geometry=self.geometry, seq=seq,
                    echoes=None if self.echo_ranges is None else self.echo_ranges.copy(),
                    echo_intensities=None if self.echo_intensities is None else self.echo_intensities.copy())


class _Optics:
    """Per-segment optical constants of a world, cached on the World object."""

    def __init__(self, world: World, params: LaserParams) -> None:
        mats = world.materials
        idx = world.segment_material
        pick = lambda f: np.array([f(m) for m in mats], dtype=np.float64)[idx]  # noqa: E731
        self.rho = pick(lambda m: m.rho)
        self.cos_k = pick(lambda m: params.cos_exponent if m.cos_exponent is None else m.cos_exponent)
        self.spec = pick(lambda m: m.specular_gain)
        self.inv2s2 = pick(lambda m: 1.0 / (2.0 * m.lobe_width ** 2))
        self.no_return = pick(lambda m: m.no_return_prob)
        self.log_t2 = pick(lambda m: 2.0 * math.log(max(m.transmission, 1e-12)))
        self.surf_rho = pick(lambda m: m.surface_rho)
        self.kind = world.segment_kind.astype(np.int64)
        seg = world.segments
        self.a = seg[:, 0].copy()
        self.e = seg[:, 1] - seg[:, 0]
        self.inv_len = 1.0 / np.hypot(self.e[:, 0], self.e[:, 1])


def _optics(world: World, params: LaserParams) -> _Optics:
    cache = world.__dict__.setdefault("_optics_cache", {})
    key = (params.cos_exponent, id(world.segments), len(world.segments))
    if key not in cache:
        cache.clear()
        cache[key] = _Optics(world, params)
    return cache[key]


def _group_first(beams: np.ndarray) -> np.ndarray:
    """Positions of the first element of each run of equal values in a sorted array."""
    if beams.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.r_[True, beams[1:] != beams[:-1]])


def cast_pairs(world: World, laser_pose: np.ndarray, geometry: LaserGeometry = LaserGeometry(),
               max_range: float = 60.0, optics: _Optics | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All (beam, segment) intersections within ``max_range``, sorted by beam then range.

    Returns (beam, segment, t, cos_incidence): beam index, segment index, range along the beam (m) and the
    cosine of the incidence angle, each of shape (h,).
    """
    opt = optics if optics is not None else _Optics(world, LaserParams())
    x, y, yaw = (float(v) for v in laser_pose)
    n = geometry.n_beams
    inc = geometry.angle_increment
    ax = opt.a[:, 0] - x
    ay = opt.a[:, 1] - y
    bx = ax + opt.e[:, 0]
    by = ay + opt.e[:, 1]
    ang_a = np.arctan2(ay, ax)
    sweep = np.arctan2(by, bx) - ang_a
    sweep = np.where(sweep > math.pi, sweep - 2 * math.pi, np.where(sweep < -math.pi, sweep + 2 * math.pi, sweep))
    start = np.where(sweep >= 0, ang_a, ang_a + sweep)
    two_pi = 2 * math.pi
    rel = np.mod(start - (yaw + geometry.angle_min), two_pi)
    width = np.abs(sweep)
    k0 = np.floor(rel / inc)
    k1 = np.ceil((rel + width) / inc)
    k0b = np.floor((rel - two_pi) / inc)
    k1b = np.ceil((rel + width - two_pi) / inc)
    lo = np.maximum(np.concatenate([k0, k0b]), 0).astype(np.int64)
    hi = np.minimum(np.concatenate([k1, k1b]), n - 1).astype(np.int64)
    cnt = np.maximum(hi - lo + 1, 0)
    m = len(ax)
    total = int(cnt.sum())
    seg = np.repeat(np.concatenate([np.arange(m), np.arange(m)]), cnt)
    ends = np.cumsum(cnt)
    beam = np.arange(total) - np.repeat(ends - cnt - lo, cnt)
    ang = yaw + geometry.angles
    dx = np.cos(ang)[beam]
    dy = np.sin(ang)[beam]
    sax = ax[seg]
    say = ay[seg]
    ex = opt.e[seg, 0]
    ey = opt.e[seg, 1]
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / den
        t = (sax * ey - say * ex) * inv
        u = (sax * dy - say * dx) * inv
    ok = (t > 1e-9) & (t <= max_range) & (u >= 0.0) & (u <= 1.0)
    beam, seg, t, den = beam[ok], seg[ok], t[ok], den[ok]
    cos_inc = np.minimum(np.abs(den) * opt.inv_len[seg], 1.0)
    # one float key (beam, then range): ranges are <= max_range, so beams stay apart; ties below ~1e-10 m
    # may come out in either order
    order = np.argsort(beam * (2.0 * max_range + 1.0) + t)
    return beam[order], seg[order], t[order], cos_inc[order]


def _cast_sweep(world: World, pose: np.ndarray, end_pose: np.ndarray, geometry: LaserGeometry, max_range: float,
                opt: _Optics, chunks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cast_pairs` for a moving laser: blocks of adjacent beams, each cast from the pose interpolated
    (position linearly, yaw along the shorter way) at the block's middle beam."""
    n = geometry.n_beams
    edges = np.linspace(0, n, max(1, min(int(chunks), n)) + 1).round().astype(np.int64)
    dyaw = math.remainder(end_pose[2] - pose[2], 2 * math.pi)
    parts = []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        f = (0.5 * (a + b - 1)) / max(n - 1, 1)
        at = np.array([pose[0] + f * (end_pose[0] - pose[0]), pose[1] + f * (end_pose[1] - pose[1]), pose[2] + f * dyaw])
        sub = replace(geometry, n_beams=int(b - a), angle_min=geometry.angle_min + a * geometry.angle_increment)
        bm, sg, tt, ci = cast_pairs(world, at, sub, max_range, opt)
        parts.append((bm + a, sg, tt, ci))
    return tuple(np.concatenate(x) for x in zip(*parts))  # type: ignore[return-value]


def simulate_scan(world: World, laser_pose, rng: np.random.Generator, params: LaserParams = LaserParams(),
                  geometry: LaserGeometry = LaserGeometry(), end_pose=None, sweep_chunks: int = 16) -> SimScan:
    """Simulate one scan from ``laser_pose`` (x, y, yaw of the laser in the map frame; m, rad).

    ``end_pose``: the laser pose when the last beam is taken; beams are then cast from poses interpolated
    linearly between the two over the sweep (in ``sweep_chunks`` blocks of adjacent beams, each from the
    pose at its middle beam), as a scanning laser on a moving robot sees the world. None (default): all
    beams from ``laser_pose`` (motion during the sweep ignored).
    """
    pose = np.asarray(laser_pose, dtype=np.float64)
    n = geometry.n_beams
    p = params
    opt = _optics(world, p)
    if end_pose is None:
        beam, seg, t, cos_inc = cast_pairs(world, pose, geometry, p.max_reading, opt)
    else:
        beam, seg, t, cos_inc = _cast_sweep(world, pose, np.asarray(end_pose, dtype=np.float64), geometry,
                                            p.max_reading, opt, sweep_chunks)
    kind = opt.kind[seg]
    glass = kind == _GLASS
    alpha = np.arccos(cos_inc)
    gain = p.intensity_scale * (p.reference_range / np.maximum(t, p.near_range)) ** p.range_exponent
    lobe = opt.spec[seg] * np.exp(-(alpha * alpha) * opt.inv2s2[seg])

    # Terminal (first opaque) hit of each beam.
    op_idx = np.flatnonzero(~glass)
    op_first = op_idx[_group_first(beam[op_idx])]
    term = np.full(n, -1, dtype=np.int64)
    term[beam[op_first]] = op_first
    t_term = np.full(n, np.inf)
    t_term[beam[op_first]] = t[op_first]

    # Glass hits in front of the terminal hit: returns or pass-through.
    g_idx = np.flatnonzero(glass & (t < t_term[beam]))
    g_beam = beam[g_idx]
    g_first = _group_first(g_beam)
    g_start = np.zeros(g_idx.size, dtype=np.int64)
    g_start[g_first] = g_first
    g_start = np.maximum.accumulate(g_start) if g_idx.size else g_start
    g_rank = np.arange(g_idx.size) - g_start  # panes crossed before this one on the same beam
    w = opt.log_t2[seg[g_idx]]
    if p.glass_fresnel_r0 is not None:
        r0 = p.glass_fresnel_r0
        refl = r0 + (1.0 - r0) * (1.0 - cos_inc[g_idx]) ** 5
        w = w + 2.0 * np.log(np.maximum((1.0 - refl) / (1.0 - r0), 1e-12))
    excl = np.cumsum(w) - w
    g_att = np.exp(excl - excl[g_start]) if g_idx.size else w
    g_t = t[g_idx]
    g_alpha = alpha[g_idx]
    window = np.maximum(p.glass_window * (p.glass_window_ref_range / np.maximum(g_t, 1e-3))
                        ** p.glass_window_exponent, p.glass_window_min)
    p_surf = p.glass_return_prob * np.clip(1.0 - (g_alpha / window) ** 2, 0.0, 1.0)
    surf = rng.random(g_idx.size) < p_surf
    g_int = gain[g_idx] * g_att * (surf * opt.surf_rho[seg[g_idx]] * cos_inc[g_idx] ** opt.cos_k[seg[g_idx]]
                                   + lobe[g_idx])
    g_int = g_int * np.exp(p.intensity_noise * rng.standard_normal(g_idx.size))
    g_ret = g_int >= p.detection_threshold
    r_idx = np.flatnonzero(g_ret)
    r_first = r_idx[_group_first(g_beam[r_idx])]
    glass_hit = np.full(n, -1, dtype=np.int64)  # position in g_idx of the first returning pane
    glass_hit[g_beam[r_first]] = r_first

    # Terminal intensity, attenuated by every pane in front of it.
    log_att = np.bincount(g_beam, weights=w, minlength=n)
    n_glass_front = np.bincount(g_beam, minlength=n)
    has_term = term >= 0
    tb = np.flatnonzero(has_term)
    ti = term[tb]
    t_int = gain[ti] * np.exp(log_att[tb]) * (opt.rho[seg[ti]] * cos_inc[ti] ** opt.cos_k[seg[ti]] + lobe[ti])
    t_int = t_int * np.exp(p.intensity_noise * rng.standard_normal(tb.size))
    t_det = (t_int >= p.detection_threshold) & (rng.random(tb.size) >= opt.no_return[seg[ti]])
    term_int = np.zeros(n)
    term_int[tb] = t_int
    term_det = np.zeros(n, dtype=bool)
    term_det[tb] = t_det

    # Primary return: the first returning pane, else the terminal hit if detected.
    from_glass = glass_hit >= 0
    gb = np.flatnonzero(from_glass)
    gpos = glass_hit[gb]
    hit = np.where(has_term, term, -1)  # index into hit arrays describing the beam's surface
    hit[gb] = g_idx[gpos]
    returned = from_glass | term_det
    intensity = np.where(term_det, term_int, 0.0)
    intensity[gb] = g_int[gpos]
    crossed = n_glass_front > 0
    crossed[gb] = g_rank[gpos] > 0

    any_hit = hit >= 0
    hi = hit[any_hit]
    true_range = np.full(n, np.inf)
    true_range[any_hit] = t[hi]
    material = np.full(n, NOTHING, dtype=np.int64)
    material[any_hit] = kind[hi]
    segment = np.full(n, -1, dtype=np.int64)
    segment[any_hit] = seg[hi]
    incidence = np.full(n, np.nan)
    incidence[any_hit] = alpha[hi]

    sigma = p.range_noise + p.range_noise_slope * np.where(np.isfinite(true_range), true_range, 0.0)
    noise = sigma * rng.standard_normal(n)
    ranges = np.where(returned, true_range + noise, np.inf)
    ranges = np.where(returned & (ranges > p.max_reading), np.inf, ranges)
    ranges = np.where(returned & (ranges < p.min_reading), np.nan, ranges)
    dropped = rng.random(n) < p.dropout_prob
    ranges[dropped] = np.nan
    intensity = np.minimum(np.where(np.isfinite(ranges), intensity, 0.0), p.saturation)

    echo_r = echo_i = None
    if p.multi_echo:
        echo_r = np.full((n, 2), np.nan)
        echo_i = np.zeros((n, 2))
        echo_r[:, 0] = ranges
        echo_i[:, 0] = intensity
        second = from_glass & term_det & ~dropped
        sb = np.flatnonzero(second)
        r2 = t_term[sb] + (p.range_noise + p.range_noise_slope * t_term[sb]) * rng.standard_normal(sb.size)
        r2 = np.where(r2 > p.max_reading, np.inf, r2)
        echo_r[sb, 1] = r2
        echo_i[sb, 1] = np.minimum(term_int[sb], p.saturation)

    return SimScan(ranges=ranges, intensities=intensity, true_range=true_range, material=material,
                   incidence=incidence, is_glass=from_glass.copy(), crossed_glass=crossed, segment=segment,
                   laser_pose=pose, geometry=geometry, echo_ranges=echo_r, echo_intensities=echo_i)
