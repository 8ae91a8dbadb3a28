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

from glassmap.sim.cast_jit import mirror_pairs
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
    multi_echo: also compute the last echo (the farthest of several detected echoes of a beam).
    mirror_reflections: model one specular bounce on glass and mirroring materials: a beam can return from
        a surface seen in the mirror and report the unfolded path length (a ghost point behind the mirror).
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
    mirror_reflections: bool = True


# beam truth classes (SimScan.truth_class)
TRUTH_NONE, TRUTH_OTHER, TRUTH_GLASS, TRUTH_GHOST = -1, 0, 1, 2


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
    is_ghost: the first echo is a mirror image: the beam was reflected by ``mirror_segment`` (a glass pane
        or a mirroring surface) and returned from the surface described by true_range / material / segment /
        incidence, true_range being the unfolded path length (laser -> mirror -> surface). The reported
        point lies behind the mirror. mirror_segment: -1 for every other beam.
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
    is_ghost: np.ndarray | None = None
    mirror_segment: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.ranges.shape[0]
        if self.is_ghost is None:
            self.is_ghost = np.zeros(n, dtype=bool)
        if self.mirror_segment is None:
            self.mirror_segment = np.full(n, -1, dtype=np.int64)

    @property
    def truth_class(self) -> np.ndarray:
        """Per beam: TRUTH_GHOST (2) mirror image, TRUTH_GLASS (1) glass, TRUTH_OTHER (0) any other return,
        TRUTH_NONE (-1) no valid reading."""
        out = np.where(self.is_ghost, TRUTH_GHOST, np.where(self.is_glass, TRUTH_GLASS, TRUTH_OTHER))
        return np.where(np.isfinite(self.ranges), out, TRUTH_NONE)

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
        self.mirror_r = pick(lambda m: 0.0 if m.is_glass else m.mirror_reflectance)
        self.kind = world.segment_kind.astype(np.int64)
        opaque = self.kind != _GLASS
        # largest diffuse + specular factor of an opaque surface: bounds what a mirror image can return
        self.max_reflect = float((self.rho + self.spec)[opaque].max()) if opaque.any() else 0.0
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


def _sweep_chunks(pose: np.ndarray, end_pose: np.ndarray, geometry: LaserGeometry, chunks: int):
    """(first beam, end beam, pose) of blocks of adjacent beams, each with the pose interpolated (position
    linearly, yaw along the shorter way) at the block's middle beam."""
    n = geometry.n_beams
    edges = np.linspace(0, n, max(1, min(int(chunks), n)) + 1).round().astype(np.int64)
    dyaw = math.remainder(end_pose[2] - pose[2], 2 * math.pi)
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        f = (0.5 * (a + b - 1)) / max(n - 1, 1)
        yield int(a), int(b), np.array([pose[0] + f * (end_pose[0] - pose[0]), pose[1] + f * (end_pose[1] - pose[1]),
                                        pose[2] + f * dyaw])


def _cast_sweep(world: World, pose: np.ndarray, end_pose: np.ndarray, geometry: LaserGeometry, max_range: float,
                opt: _Optics, chunks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cast_pairs` for a moving laser: blocks of adjacent beams, each cast from its block's pose."""
    parts = []
    for a, b, at in _sweep_chunks(pose, end_pose, geometry, chunks):
        sub = replace(geometry, n_beams=b - a, angle_min=geometry.angle_min + a * geometry.angle_increment)
        bm, sg, tt, ci = cast_pairs(world, at, sub, max_range, opt)
        parts.append((bm + a, sg, tt, ci))
    return tuple(np.concatenate(x) for x in zip(*parts))  # type: ignore[return-value]


def cast_mirrored(opt: _Optics, pose: np.ndarray, geometry: LaserGeometry, beams: np.ndarray, mirror: np.ndarray,
                  t_mirror: np.ndarray, max_range: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Intersections of reflected beams with the world, sorted by beam then path length.

    Beam ``beams[i]`` of a laser at ``pose`` is reflected by segment ``mirror[i]`` at range ``t_mirror[i]``.
    Reflecting the laser across the mirror's line gives a virtual laser from which the reflected ray is a
    straight ray; its hits beyond the mirror are the surfaces seen in the mirror, at the unfolded path
    length. As in :func:`cast_pairs`, each (mirror, segment) pair is first mapped to the interval of beam
    indices it can meet, and only those (beam, segment) pairs are intersected. Returns (beam, segment,
    path length (m), cosine of the incidence angle on that segment), each (h,).
    """
    x, y, yaw = (float(v) for v in pose)
    n = geometry.n_beams
    inc = geometry.angle_increment
    two_pi = 2 * math.pi
    mirrors, inv = np.unique(mirror, return_inverse=True)
    nm = mirrors.size
    bmin = np.full(nm, n, dtype=np.int64)
    bmax = np.full(nm, -1, dtype=np.int64)
    np.minimum.at(bmin, inv, beams)
    np.maximum.at(bmax, inv, beams)
    ux = opt.e[mirrors, 0] * opt.inv_len[mirrors]
    uy = opt.e[mirrors, 1] * opt.inv_len[mirrors]
    dist = (x - opt.a[mirrors, 0]) * -uy + (y - opt.a[mirrors, 1]) * ux  # signed distance to the mirror line
    vx = x + 2.0 * dist * uy  # the virtual laser: the laser reflected across the mirror's line
    vy = y - 2.0 * dist * ux
    phi2 = 2.0 * np.arctan2(uy, ux)
    # angular interval of every segment seen from every virtual laser: (mirrors, segments)
    ax = opt.a[None, :, 0] - vx[:, None]
    ay = opt.a[None, :, 1] - vy[:, None]
    ang_a = np.arctan2(ay, ax)
    sweep = np.arctan2(ay + opt.e[None, :, 1], ax + opt.e[None, :, 0]) - ang_a
    sweep = np.where(sweep > math.pi, sweep - two_pi, np.where(sweep < -math.pi, sweep + two_pi, sweep))
    start = np.where(sweep >= 0, ang_a, ang_a + sweep)
    width = np.abs(sweep)
    # reflected direction of beam b: phi2 - (yaw + angle_min + b inc); inside [start, start + width] when
    # b inc lies in [phi2 - yaw - angle_min - start - width, ... + width] (mod 2 pi)
    rel = np.mod(phi2[:, None] - yaw - geometry.angle_min - start - width, two_pi)
    k0 = np.floor(rel / inc)
    k1 = np.ceil((rel + width) / inc)
    k0b = np.floor((rel - two_pi) / inc)
    k1b = np.ceil((rel + width - two_pi) / inc)
    # the reflected ray stays on the laser's side of the mirror: segments wholly behind it are never hit
    sa = (opt.a[None, :, 0] - opt.a[mirrors, 0][:, None]) * -uy[:, None] + (
        opt.a[None, :, 1] - opt.a[mirrors, 1][:, None]) * ux[:, None]
    sb = sa + opt.e[None, :, 0] * -uy[:, None] + opt.e[None, :, 1] * ux[:, None]
    side = np.sign(dist)[:, None]
    front = np.maximum(sa * side, sb * side) > 1e-9
    # the (beam, mirror, segment) triples of each mirror's beams and the segments in front of it (compiled)
    beam_mirror = np.full(n, -1, dtype=np.int64)
    beam_mirror[beams] = inv
    t_min = np.zeros(n)
    t_min[beams] = t_mirror
    bb, jj, kk = mirror_pairs(k0, k1, k0b, k1b, front, bmin, bmax, beam_mirror, mirrors)
    ang = phi2[jj] - (yaw + geometry.angles[bb])
    dx = np.cos(ang)
    dy = np.sin(ang)
    sax = opt.a[kk, 0] - vx[jj]
    say = opt.a[kk, 1] - vy[jj]
    ex = opt.e[kk, 0]
    ey = opt.e[kk, 1]
    den = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        invd = 1.0 / den
        t = (sax * ey - say * ex) * invd
        u = (sax * dy - say * dx) * invd
    ok = (t > t_min[bb] + 1e-6) & (t <= max_range) & (u >= 0.0) & (u <= 1.0)
    bb, kk, t, den = bb[ok], kk[ok], t[ok], den[ok]
    cos_inc = np.minimum(np.abs(den) * opt.inv_len[kk], 1.0)
    order = np.argsort(bb * (2.0 * max_range + 1.0) + t)
    return bb[order], kk[order], t[order], cos_inc[order]


def world_laser_params(world: World, base: LaserParams | None = None) -> LaserParams:
    """``base`` (default: ``LaserParams()``) with the world's ``[laser]`` overrides applied."""
    b = base if base is not None else LaserParams()
    return replace(b, **world.laser) if world.laser else b


def simulate_scan(world: World, laser_pose, rng: np.random.Generator, params: LaserParams | None = None,
                  geometry: LaserGeometry = LaserGeometry(), end_pose=None, sweep_chunks: int = 16) -> SimScan:
    """Simulate one scan from ``laser_pose`` (x, y, yaw of the laser in the map frame; m, rad).

    ``params``: the laser model; None = ``world_laser_params(world)`` (defaults plus the world's overrides).

    ``end_pose``: the laser pose when the last beam is taken; beams are then cast from poses interpolated
    linearly between the two over the sweep (in ``sweep_chunks`` blocks of adjacent beams, each from the
    pose at its middle beam), as a scanning laser on a moving robot sees the world. None (default): all
    beams from ``laser_pose`` (motion during the sweep ignored).
    """
    pose = np.asarray(laser_pose, dtype=np.float64)
    n = geometry.n_beams
    p = params if params is not None else world_laser_params(world)
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

    # Random draws of the range noise and dropouts (before the mirror images' draws).
    z_range = rng.standard_normal(n)
    dropped = rng.random(n) < p.dropout_prob

    # Mirror images: one specular bounce on the first mirroring surface of each beam.
    ghost_t = np.full(n, np.inf)
    ghost_int = np.zeros(n)
    ghost_seg = np.full(n, -1, dtype=np.int64)
    ghost_cos = np.ones(n)
    mirror_seg = np.full(n, -1, dtype=np.int64)
    if p.mirror_reflections and opt.max_reflect > 0:
        mir = np.full(n, -1, dtype=np.int64)  # index into the hit arrays of the mirroring surface
        tb_m = tb[opt.mirror_r[seg[ti]] > 0]
        mir[tb_m] = term[tb_m]
        if g_idx.size:
            mir[g_beam[g_first]] = g_idx[g_first]  # the first pane in front of the terminal hit
        mb = np.flatnonzero(mir >= 0)
        mh = mir[mb]
        r0 = p.glass_fresnel_r0 if p.glass_fresnel_r0 is not None else 0.04
        refl = np.where(kind[mh] == _GLASS, r0 + (1.0 - r0) * (1.0 - cos_inc[mh]) ** 5, opt.mirror_r[seg[mh]])
        # an image can only be detected if the brightest opaque surface at the mirror's range would be
        # (the distance term only falls with the longer path; noise bound 4 sigma)
        bound = gain[mh] * refl * refl * opt.max_reflect * math.exp(4.0 * p.intensity_noise)
        keep = bound >= p.detection_threshold
        mb, mh, refl = mb[keep], mh[keep], refl[keep]
        if mb.size:
            if end_pose is None:
                parts = [cast_mirrored(opt, pose, geometry, mb, seg[mh], t[mh], p.max_reading)]
            else:
                parts = []
                for a0, b0, at in _sweep_chunks(pose, np.asarray(end_pose, dtype=np.float64), geometry,
                                                sweep_chunks):
                    sel = (mb >= a0) & (mb < b0)
                    if sel.any():
                        parts.append(cast_mirrored(opt, at, geometry, mb[sel], seg[mh[sel]], t[mh[sel]],
                                                   p.max_reading))
            if parts:
                bm2, sg2, t2, c2 = (np.concatenate(x) for x in zip(*parts))
            else:
                bm2 = sg2 = np.zeros(0, dtype=np.int64)
                t2 = c2 = np.zeros(0)
            glass2 = opt.kind[sg2] == _GLASS
            op2 = np.flatnonzero(~glass2)
            q = op2[_group_first(bm2[op2])]  # first opaque surface seen in the mirror
            q_end = np.full(n, np.inf)
            q_end[bm2[q]] = t2[q]
            pane2 = glass2 & (t2 < q_end[bm2])  # panes on the reflected path attenuate it
            att2 = np.bincount(bm2[pane2], weights=opt.log_t2[sg2[pane2]], minlength=n)
            refl_b = np.zeros(n)
            refl_b[mb] = refl
            qb, qs, qt, qc = bm2[q], sg2[q], t2[q], c2[q]
            qa = np.arccos(qc)
            q_int = (p.intensity_scale * (p.reference_range / np.maximum(qt, p.near_range)) ** p.range_exponent
                     * refl_b[qb] ** 2 * np.exp(att2[qb])
                     * (opt.rho[qs] * qc ** opt.cos_k[qs] + opt.spec[qs] * np.exp(-(qa * qa) * opt.inv2s2[qs])))
            q_int = q_int * np.exp(p.intensity_noise * rng.standard_normal(qb.size))
            q_det = (q_int >= p.detection_threshold) & (rng.random(qb.size) >= opt.no_return[qs])
            qb, qs, qt, qc, q_int = qb[q_det], qs[q_det], qt[q_det], qc[q_det], q_int[q_det]
            ghost_t[qb] = qt
            ghost_int[qb] = q_int
            ghost_seg[qb] = qs
            ghost_cos[qb] = qc
            mirror_seg[qb] = seg[mir[qb]]

    # Echoes: the first returning pane, the terminal hit if detected, the mirror image if detected; the
    # first echo is the nearest.
    from_pane = glass_hit >= 0
    gb = np.flatnonzero(from_pane)
    gpos = glass_hit[gb]
    cand_t = np.full((3, n), np.inf)
    cand_t[0, gb] = t[g_idx[gpos]]
    cand_t[1] = np.where(term_det, t_term, np.inf)
    cand_t[2] = ghost_t
    cand_i = np.zeros((3, n))
    cand_i[0, gb] = g_int[gpos]
    cand_i[1] = np.where(term_det, term_int, 0.0)
    cand_i[2] = ghost_int
    first = np.argmin(cand_t, axis=0)
    n_echo = np.isfinite(cand_t).sum(axis=0)
    returned = n_echo > 0
    from_glass = returned & (first == 0)
    ghost = returned & (first == 2)
    cols = np.arange(n)

    hit = np.where(has_term, term, -1)  # index into hit arrays describing the beam's surface
    hit[from_glass] = g_idx[glass_hit[from_glass]]
    intensity = np.where(returned, cand_i[first, cols], 0.0)
    crossed = n_glass_front > 0
    crossed[from_glass] = g_rank[glass_hit[from_glass]] > 0
    crossed[ghost] = False

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
    true_range[ghost] = ghost_t[ghost]
    material[ghost] = opt.kind[ghost_seg[ghost]]
    segment[ghost] = ghost_seg[ghost]
    incidence[ghost] = np.arccos(ghost_cos[ghost])
    mirror_seg[~ghost] = -1

    sigma = p.range_noise + p.range_noise_slope * np.where(np.isfinite(true_range), true_range, 0.0)
    noise = sigma * z_range
    ranges = np.where(returned, true_range + noise, np.inf)
    ranges = np.where(returned & (ranges > p.max_reading), np.inf, ranges)
    ranges = np.where(returned & (ranges < p.min_reading), np.nan, ranges)
    ranges[dropped] = np.nan
    intensity = np.minimum(np.where(np.isfinite(ranges), intensity, 0.0), p.saturation)

    echo_r = echo_i = None
    if p.multi_echo:
        echo_r = np.full((n, 2), np.nan)
        echo_i = np.zeros((n, 2))
        echo_r[:, 0] = ranges
        echo_i[:, 0] = intensity
        z_echo = rng.standard_normal(n)
        sb = np.flatnonzero((n_echo >= 2) & ~dropped)
        last = np.argmax(np.where(np.isfinite(cand_t), cand_t, -1.0), axis=0)[sb]
        t_last = cand_t[last, sb]
        r2 = t_last + (p.range_noise + p.range_noise_slope * t_last) * z_echo[sb]
        r2 = np.where(r2 > p.max_reading, np.inf, r2)
        echo_r[sb, 1] = r2
        echo_i[sb, 1] = np.minimum(cand_i[last, sb], p.saturation)

    return SimScan(ranges=ranges, intensities=intensity, true_range=true_range, material=material,
                   incidence=incidence, is_glass=from_glass, crossed_glass=crossed, segment=segment,
                   laser_pose=pose, geometry=geometry, echo_ranges=echo_r, echo_intensities=echo_i,
                   is_ghost=ghost, mirror_segment=mirror_seg)
