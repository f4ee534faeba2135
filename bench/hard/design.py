"""The suite's fractional design: which geometry each lighting condition is rendered with.

Full factorial would be 16 lightings x 3 rotations x 3 objects x 3 camera elevations x 2 albedo pairs x 2 noise
levels = 1,728 solves and 864 path-traced renders (~3 h of renders alone here). Instead every lighting x rotation
(48 renders) gets ONE geometry configuration (object, camera elevation, albedo pair), chosen so that for every
lighting its three rotations see all three objects and all three elevations, and over the suite every object
meets every albedo pair equally often:

    object = OBJECTS[(l + k) % 3], elevation = ELEVATIONS[(l + 2k) % 3], albedo = ALBEDOS[(l + k) % 2]

(l the lighting's index, k the rotation's). Both noise levels are two targets of one render (one clean image, two
independent noise draws) and share one A. Lightings of one geometry configuration are targets of one capture, so
A is built once per configuration (at most 18 A for 96 solves). ``--quick``: four lightings (a lamp at 3 degrees,
the two-lamp room, the low sun, forest) at rotation 0 on 64 x 64 images at 256 spp.

``HELD_OUT`` (``--design held-out``) is the same construction on everything the suite's rules were not chosen on:
three other objects (a trefoil knot, a mug, a sphere), camera elevations 28, 45 and 75 degrees, mid-contrast
albedo pairs (0.3 on 0.7, 0.7 on 0.25), rotations 60, 200 and 310 degrees, and 14 lightings with knobs the suite
never had (bench.hard.lighting.held_out_lightings: other lamp elevations, rooms, window and suns, an overcast sky,
the three CC0 HDRIs objcam does not bundle): 42 renders, 84 targets. No parameter is chosen on it; it says whether
the suite's choices hold.
"""

from __future__ import annotations

from dataclasses import dataclass

from bench.hard.lighting import Lighting, held_out_lightings, lightings
from bench.hard.objects import HELD_OUT_OBJECTS, OBJECTS

ELEVATIONS = (20.0, 35.0, 60.0)
ALBEDOS = ((0.05, 0.8), (0.8, 0.05))  # (object, support): a dark object on a bright plane, and the reverse
ROTATIONS = (0.0, 137.0, 251.0)  # degrees; not multiples of the solve's 5.6-degree texels
NOISES = (0.005, 0.02)  # zero-mean Gaussian, relative to the median pixel; negatives kept
QUICK = ("lamp3", "room2", "sun8", "forest")


@dataclass(frozen=True)
class Design:
    """What a design crosses: its lightings, and the object, camera elevation, albedo pair and rotation slots
    (three objects, three elevations, two albedo pairs, three rotations)."""

    name: str
    lightings: tuple[Lighting, ...]
    objects: tuple[str, ...]
    elevations: tuple[float, ...]
    albedos: tuple[tuple[float, float], ...]
    rotations: tuple[float, ...]


SUITE = Design("suite", tuple(lightings()), OBJECTS, ELEVATIONS, ALBEDOS, ROTATIONS)
HELD_OUT = Design("held-out", tuple(held_out_lightings()), HELD_OUT_OBJECTS, (28.0, 45.0, 75.0),
                  ((0.3, 0.7), (0.7, 0.25)), (60.0, 200.0, 310.0))
DESIGNS = {d.name: d for d in (SUITE, HELD_OUT)}


@dataclass(frozen=True)
class Geometry:
    """One geometry configuration: what A depends on."""

    object: str
    elevation_deg: float
    albedo_object: float
    albedo_support: float

    @property
    def key(self) -> str:
        dark = "dark" if self.albedo_object < self.albedo_support else "light"
        return f"{self.object}-el{self.elevation_deg:g}-{dark}"

    @property
    def albedo_label(self) -> str:
        return f"{self.albedo_object:g} on {self.albedo_support:g}"


@dataclass(frozen=True)
class Case:
    """One render: a lighting at a rotation on a geometry; solved at every noise level of :data:`NOISES`."""

    light: Lighting
    rotation_deg: float
    geometry: Geometry

    @property
    def name(self) -> str:
        return f"{self.light.name}_r{self.rotation_deg:g}"

    def target(self, noise: float) -> str:
        return f"{self.name}_n{100 * noise:g}"


def cases(quick: bool = False, rotations: tuple[float, ...] | None = None, design: Design = SUITE) -> list[Case]:
    """The renders of ``design`` (``quick``: the suite's development subset). ``rotations``: three others than the
    design's (a held-out check of a rule chosen on the suite: the same lightings, objects, cameras and albedos,
    each lighting turned where the suite never had it)."""
    rotations = design.rotations if rotations is None else tuple(rotations)
    if len(rotations) != len(design.rotations):
        raise ValueError(f"rotations: {len(design.rotations)} angles (one per geometry slot), got {len(rotations)}")
    out = []
    for li, light in enumerate(design.lightings):
        for k, rot in enumerate(rotations):
            if quick and (light.name not in QUICK or k > 0):
                continue
            a_obj, a_sup = design.albedos[(li + k) % 2]
            geo = Geometry(design.objects[(li + k) % 3], design.elevations[(li + 2 * k) % 3], a_obj, a_sup)
            out.append(Case(light, rot, geo))
    return out
