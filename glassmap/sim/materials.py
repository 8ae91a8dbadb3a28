"""Surface materials of the simulated world and their optical parameters.

Every surface returns a *diffuse* part and a *specular lobe* (see ``glassmap.sim.laser`` for the full
intensity model):

    I = K * gain_r * (rho * cos^k(alpha) + specular_gain * exp(-alpha^2 / (2 * lobe_width^2)))

with alpha the incidence angle (rad, 0 = beam along the surface normal) and gain_r the distance term of the
laser. Glass is special: its diffuse part (``surface_rho``) only appears inside a distance-dependent angular
window and with a probability (a weak surface return); otherwise the beam passes through with
``transmission`` (per pass) and ranges what is behind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum


class MaterialKind(IntEnum):
    """Material kind codes used in per-beam ground truth (``SimScan.material``); -1 means nothing hit."""

    WALL = 0  # ordinary diffuse wall (plaster, concrete, painted)
    GLASS = 1  # glass pane (facade, partition, door)
    FRAME = 2  # window frame / mullion between panes (not glass)
    METAL = 3  # polished metal (elevator doors, steel panels): specular distractor
    WHITEBOARD = 4  # whiteboard / glossy paint: wider, weaker specular distractor
    RETRO = 5  # retroreflective tape: bright at every angle
    DARK = 6  # dark furniture / fabric: low reflectivity, sometimes no return
    OBJECT = 7  # ordinary furniture / objects (diffuse)


NOTHING = -1
"""Material code of a beam that hit nothing."""


@dataclass(frozen=True)
class Material:
    """Optical parameters of one surface material (dimensionless unless stated).

    rho: diffuse reflectivity (0..1; retroreflective tape is > 1 because it sends light back).
    cos_exponent: k in cos^k(alpha) of the diffuse part; None = the laser's default (LaserParams.cos_exponent).
    specular_gain: peak of the specular lobe relative to a rho = 1 diffuse surface at normal incidence.
    lobe_width: standard deviation of the specular lobe in incidence angle (rad).
    no_return_prob: extra probability that a hit on this material gives no return at all (dark fabric).
    transmission: GLASS only, fraction of the power that passes one pane (per pass; a return from behind is
        attenuated by transmission^2 per pane crossed).
    surface_rho: GLASS only, reflectivity of the weak surface return inside the angular window.
    mirror_reflectance: fraction of the power a non-glass surface reflects as a mirror (one specular bounce,
        independent of the angle; polished metal). Glass reflects by Fresnel's law instead (see
        ``LaserParams.glass_fresnel_r0``).
    """

    name: str
    kind: MaterialKind
    rho: float = 0.6
    cos_exponent: float | None = None
    specular_gain: float = 0.0
    lobe_width: float = math.radians(1.0)
    no_return_prob: float = 0.0
    transmission: float = 0.0
    surface_rho: float = 0.0
    mirror_reflectance: float = 0.0

    def __post_init__(self) -> None:
        if self.rho < 0 or self.specular_gain < 0 or self.surface_rho < 0:
            raise ValueError(f"material {self.name!r}: rho, specular_gain and surface_rho must be >= 0")
        if not all(0 <= v <= 1 for v in (self.no_return_prob, self.transmission, self.mirror_reflectance)):
            raise ValueError(f"material {self.name!r}: no_return_prob, transmission and mirror_reflectance must "
                             f"be in [0, 1]")
        if self.lobe_width <= 0:
            raise ValueError(f"material {self.name!r}: lobe_width must be > 0 rad")
        if self.cos_exponent is not None and self.cos_exponent < 0:
            raise ValueError(f"material {self.name!r}: cos_exponent must be >= 0")

    @property
    def is_glass(self) -> bool:
        return self.kind == MaterialKind.GLASS


# Defaults per kind. A world file picks a kind and may override any field (see docs/simulator.md).
KIND_DEFAULTS: dict[MaterialKind, dict[str, float]] = {
    MaterialKind.WALL: dict(rho=0.65),
    # Glass: very bright, very narrow specular peak (sigma 0.3 deg: a few 0.25 deg beams above the
    # saturation level at short range), a weak surface return (surface_rho) inside the angular window,
    # 92 % transmission per pass.
    MaterialKind.GLASS: dict(rho=0.0, specular_gain=40.0, lobe_width=math.radians(0.3), transmission=0.92,
                             surface_rho=0.12),
    MaterialKind.FRAME: dict(rho=0.45, specular_gain=0.3, lobe_width=math.radians(3.0)),
    # Polished metal: weak diffuse part, a bright lobe a few degrees wide, half the power mirrored.
    MaterialKind.METAL: dict(rho=0.25, specular_gain=8.0, lobe_width=math.radians(2.5), mirror_reflectance=0.5),
    # Whiteboard: bright diffuse part plus a wider, weaker lobe.
    MaterialKind.WHITEBOARD: dict(rho=0.8, specular_gain=2.5, lobe_width=math.radians(4.0)),
    # Retroreflective tape: very bright almost independent of angle.
    MaterialKind.RETRO: dict(rho=6.0, cos_exponent=0.2),
    MaterialKind.DARK: dict(rho=0.06, no_return_prob=0.15),
    MaterialKind.OBJECT: dict(rho=0.45),
}


def default_material(name: str, kind: MaterialKind) -> Material:
    """A material of ``kind`` with that kind's default parameters."""
    return Material(name=name, kind=kind, **KIND_DEFAULTS[kind])  # type: ignore[arg-type]


# Materials every world has without declaring them; a world file may redefine them or add more.
BUILTIN_MATERIALS: dict[str, Material] = {
    "wall": default_material("wall", MaterialKind.WALL),
    "glass": default_material("glass", MaterialKind.GLASS),
    "frame": default_material("frame", MaterialKind.FRAME),
    "metal": default_material("metal", MaterialKind.METAL),
    "whiteboard": default_material("whiteboard", MaterialKind.WHITEBOARD),
    "retro": default_material("retro", MaterialKind.RETRO),
    "dark": default_material("dark", MaterialKind.DARK),
    "object": default_material("object", MaterialKind.OBJECT),
}

KIND_BY_NAME: dict[str, MaterialKind] = {k.name.lower(): k for k in MaterialKind}
