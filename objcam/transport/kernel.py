"""``transport.texel_kernel``: box texels or a narrow kernel, by the fit (``auto`` and ``fit``).

A column of A is the image of one texel's radiance. With box texels (kernel 1) the shadow rays sample the whole
texel, so a column is the light of a uniformly bright 5.6-deg patch (at 32 x 64) and its shadows have a 5.6-deg
penumbra. A source smaller than a texel (a lamp, the sun) casts sharper shadows than any box column: a fit with
box columns can sharpen a shadow only by negative lobes beside the bright texel, which x >= 0 clips to black (the
black rings of the suite's lamps and rooms, bench/results.md, session 27). A narrow kernel (the rays aim into the
central ``NARROW`` of the texel per side) gives sharp columns; a compact source between two texel centres is then
a non-negative mix of two of them. But under an extended source (a window, an overcast sky) seen past a thin
occluder, narrow columns alias: the sum of sharp shadows is a comb where the photo holds a smooth penumbra.

Neither is right for every sky, and the sky is what the solve finds. ``fit`` solves every target on both A's (the
default solve, objcam.solvers.plan.solve_capture) and keeps the A whose fit leaves the lower chi-squared per
fitted value (the verdict's ``chi2``: the residual against the stated noise). ``auto`` (the default) solves each
target on the box A and builds the narrow A only for a camera where a target's solve left black sky (its
``dark_sky_area`` above ``DARK_TRIGGER``): those targets then take the lower chi2. Both A's come from the same seeds
(the narrow directions are the box's mapped into the texel's centre), so their difference is the kernel, not
Monte Carlo noise. A target whose albedo is unknown shares its camera's A with the other targets of that camera
(the joint solve ties them by the albedo), so there the camera chooses, by the chi-squared summed over its
targets. Measured on the hard suite (bench/results.md, issue 22, session 28), against box texels alone: ``fit``
median SSIM 0.777 -> 0.789, the worst 0.002 -> 0.288, 39 targets better and 9 worse (by 0.098 at most), but on
the core bench's 0.1%-noise captures forest and courtyard lose 0.01-0.02; ``auto`` gives 8 of 96 targets the narrow
A, all rooms (the worst 0.002 -> 0.290, rooms median 0.327 -> 0.426; 6 better, 2 worse by 0.098 and 0.010) and no
core bench or demo target (their box solves leave no black sky).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from objcam.solvers.plan.defaults import VERDICT_DARK_YELLOW

#: the narrow kernel's width, a fraction of the texel per side (0.25: 1.4 deg at 32 x 64, under the 2-deg lamps
#: of the suite; 0.5 recovered less of the rooms, bench/results.md)
NARROW = 0.25
#: ``auto`` builds the narrow A only where the box A's solve left more of the sky black than this (the verdict's
#: yellow line, objcam.solvers.plan.defaults.VERDICT_DARK_YELLOW): on the hard suite 10 of 96 targets, all
#: rooms; no core bench or demo target
DARK_TRIGGER = VERDICT_DARK_YELLOW


def pilot(scene, targets: list, folder: Path, capture: Path) -> dict[str, dict]:
    """{target: {"chi2", "values", "dark_sky_area"}} of the default solve of ``targets`` on the A in ``folder``
    (the verdict's chi2 per fitted value and its share of black sky, objcam.solvers.plan.verdict)."""
    from objcam.solvers.plan.capture import solve_capture
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from objcam.transport.pixels import target_rows
    from objcam.transport.storage import load_group

    tr = load_group(folder)
    data = {t.name: TargetData(tr, *target_rows(t.load_image(scene.folder), t.load_valid(scene.folder),
                                                tr.downsample, tr.pixel_index)) for t in targets}
    sols = solve_capture(scene.model_copy(update={"targets": list(targets)}), data, SolveParams(), capture)
    out = {}
    for t in targets:
        v = sols[t.name].info.get("verdict", {})
        out[t.name] = {"chi2": float(v.get("chi2", np.inf)), "values": int(data[t.name].use.sum()) * 3,
                       "dark_sky_area": float(v.get("dark_sky_area", 0.0))}
    return out


def triggered(box: dict[str, dict]) -> list[str]:
    """``auto``: the targets whose box solve left more than ``DARK_TRIGGER`` of the sky black (the rings)."""
    return [name for name, p in box.items() if p["dark_sky_area"] > DARK_TRIGGER]


def choose(box: dict[str, dict], narrow: dict[str, dict], names: list[str], joint: bool) -> dict[str, dict]:
    """Per target of one camera (pilot results on both A's), {"chi2_box", "chi2_narrow", "kernel"}: the narrow
    kernel where its chi2 is lower, for the targets ``names`` (the rest keep box texels).

    joint: the targets' albedo is unknown: one choice for the camera, by the chi2 summed over its targets.
    """
    rec = {n: {"chi2_box": round(box[n]["chi2"], 5), "dark_sky_area_box": round(box[n]["dark_sky_area"], 5),
               "kernel": 1.0} for n in box}
    for n in narrow:
        rec[n]["chi2_narrow"] = round(narrow[n]["chi2"], 5)
    if joint:
        sb = sum(box[n]["chi2"] * box[n]["values"] for n in narrow)
        sn = sum(narrow[n]["chi2"] * narrow[n]["values"] for n in narrow)
        take = list(narrow) if sn < sb else []
    else:
        take = [n for n in names if narrow[n]["chi2"] < box[n]["chi2"]]
    for n in take:
        rec[n]["kernel"] = NARROW
    return rec


def for_camera(art, geo, targets: list, out: Path, sub: str, settings, valids, noise, model_choice: str | None,
               mapping: dict[str, str], mode: str, capture: Path) -> dict:
    """The transport stage's ``auto`` / ``fit`` for one camera whose box A is built in ``out / sub``: solve its
    targets on it; where ``mode`` asks, build the narrow kernel's A beside it (``sub`` + "k": the same settings,
    seeds and auto model choice ``model_choice``), give each target the A its fit prefers (``mapping``: target ->
    group, updated) and delete an A no target took. Returns the camera's metrics (``texel_kernel_auto``)."""
    import dataclasses
    import shutil

    from objcam.transport.build import build_camera
    from objcam.transport.engine import current

    try:  # a capture the solve refuses (no usable pixel, say) is the solve stage's to report: keep box texels
        box = pilot(art, targets, out / sub, capture)
    except Exception as e:  # noqa: BLE001
        return {"texel_kernel_auto": {"mode": mode, "skipped": f"{type(e).__name__}: {e}"[:300]}}
    names = [t.name for t in targets] if mode == "fit" else triggered(box)
    rec = {"mode": mode, "targets": {n: {"dark_sky_area_box": round(p["dark_sky_area"], 5), "kernel": 1.0}
                                     for n, p in box.items()}}
    if not names:
        return {"texel_kernel_auto": rec}
    narrow = dataclasses.replace(settings, texel_kernel=NARROW,
                                 auto_choice=model_choice if settings.model == "auto" else None)
    mk = build_camera(geo, targets[0].camera, out / (sub + "k"), narrow, valids=valids,
                      targets=[t.name for t in targets], target_noise=noise)
    current().write_gram(out / (sub + "k"))
    joint = not (art.description.albedo_object.known and art.description.albedo_support.known)
    asked = targets if joint else [t for t in targets if t.name in names]
    rec["targets"] = choose(box, pilot(art, asked, out / (sub + "k"), capture), names, joint)
    mapping.update({n: sub + "k" for n, r in rec["targets"].items() if r["kernel"] < 1})
    for s in (sub, sub + "k"):
        if s not in mapping.values():
            shutil.rmtree(out / s)
    return {"texel_kernel_auto": rec, "seconds_narrow": mk.get("seconds")}
