"""Which reflectance a probe's ball is given, and the record of it that probe.json keeps.

The normal-incidence value: the manifest's ``reflectance`` (the ball's measured reflectance), else the stage's
``default_reflectance``, else chromium's own (:data:`CHROMIUM`). The angular shape (``fresnel``): chromium's
conductor Fresnel curve (remapped to a given normal-incidence value), Schlick's approximation, or none
(:class:`objcam.probe.optics.Reflectance`).
"""

from __future__ import annotations

from objcam.probe.optics import Reflectance

CHROMIUM = "chromium's measured optical constants (Mitsuba 'Cr'; normal-incidence reflectance 0.69, 0.65, 0.69)"


def choose_reflectance(manifest: float | None, default: float | None, fresnel: str) -> tuple[Reflectance, dict]:
    """The ball's :class:`Reflectance` from the manifest's normal-incidence value ``manifest``, else the stage's
    ``default``, else chromium's, with the angular shape ``fresnel`` ("conductor", "schlick" or "none"); and its
    record (the reflectance's own dict plus ``source``, ``f0`` (3,) and a ``note`` on the shape)."""
    if manifest is not None:
        value, source = manifest, "manifest (capture.toml [[probes]] reflectance)"
    elif default is not None:
        value, source = default, "probe.default_reflectance"
    else:
        value, source = None, "default: " + CHROMIUM
    if value is None and fresnel != "conductor":
        value = tuple(float(x) for x in Reflectance(None, "conductor").f0())  # chromium's F0 with another shape
    refl = Reflectance(value, fresnel)
    note = {"conductor": "Fresnel: chromium's conductor curve"
                         + (" remapped to the given normal-incidence value" if value is not None else "")
                         + " (flat to ~40 deg, a dip near 75 deg, 1 at grazing)",
            "schlick": "Fresnel: Schlick's approximation (no conductor dip; up to 0.19 high near 80 deg)",
            "none": "no Fresnel: constant reflectance at every incidence angle"}[fresnel]
    return refl, dict(refl.to_dict(), source=source, f0=refl.f0().tolist(), note=note)
