"""``transport.texel_kernel=auto``: box texels or a narrow kernel, chosen per target by the fit.

A column of A is the image of one texel's radiance. With box texels (kernel 1) the shadow rays sample the whole
texel, so a column is the light of a uniformly bright 5.6-deg patch (at 32 x 64) and its shadows have a 5.6-deg
penumbra. A source smaller than a texel (a lamp, the sun) casts sharper shadows than any box column: a fit with
box columns can sharpen a shadow only by negative lobes beside the bright texel, which x >= 0 clips to black (the
black rings of the suite's lamps and rooms, bench/results.md, session 27). A narrow kernel (the rays aim into the
central ``NARROW`` of the texel per side) gives sharp columns; a compact source between two texel centres is then
a non-negative mix of two of them. But under an extended source (a window, an overcast sky) seen past a thin
occluder, narrow columns alias: the sum of sharp shadows is a comb where the photo holds a smooth penumbra.

Neither is right for every sky, and the sky is what the solve finds, so each target is solved with both (the
default solve, objcam.solvers.plan.solve_capture) and keeps the A whose fit leaves the lower chi-squared per
fitted value (the verdict's ``chi2``: the residual against the stated noise). Both A's come from the same seeds
(the narrow directions are the box's mapped into the texel's centre), so their difference is the kernel, not
Monte Carlo noise. A target whose albedo is unknown shares its camera's A with the other targets of that camera
(the joint solve ties them by the albedo), so there the camera chooses, by the chi-squared summed over its
targets. Measured on the hard suite (bench/results.md, issue 22, session 28): median SSIM 0.777 -> 0.789, the
worst 0.002 -> 0.288, 39 targets better and 9 worse (by 0.098 at most) against the box kernel alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the narrow kernel's width, a fraction of the texel per side (0.25: 1.4 deg at 32 x 64, under the 2-deg lamps
#: of the suite; 0.5 recovered less of the rooms, bench/results.md)
NARROW = 0.25


def _chi2(scene, targets: list, folder: Path, capture: Path) -> dict[str, tuple[float, int]]:
    """{target: (chi2 per fitted value, fitted values)} of the default solve of ``targets`` on the A in
    ``folder``."""
    from objcam.solvers.plan.capture import solve_capture
    from objcam.solvers.plan.params import SolveParams
    from objcam.solvers.plan.targets import TargetData
    from objcam.transport.pixels import target_rows
    from objcam.transport.storage import load_group

    tr = load_group(folder)
    data = {t.name: TargetData(tr, *target_rows(t.load_image(scene.folder), t.load_valid(scene.folder),
                                                tr.downsample, tr.pixel_index)) for t in targets}
    sub = scene.model_copy(update={"targets": list(targets)})
    sols = solve_capture(sub, data, SolveParams(), capture)
    out = {}
    for t in targets:
        v = sols[t.name].info.get("verdict", {})
        out[t.name] = (float(v.get("chi2", np.inf)), int(data[t.name].use.sum()) * 3)
    return out


def choose(scene, targets: list, box: Path, narrow: Path, joint: bool, capture: Path) -> tuple[dict[str, str], dict]:
    """Per target of one camera, ``box.name`` or ``narrow.name`` (the A group it is solved with) and the record.

    joint: the targets' albedo is unknown (one choice for the camera, by the summed chi-squared); capture: the
    capture folder (for the solve's error messages).
    """
    cb, cn = _chi2(scene, targets, box, capture), _chi2(scene, targets, narrow, capture)
    rec = {t.name: {"chi2_box": round(cb[t.name][0], 5), "chi2_narrow": round(cn[t.name][0], 5)} for t in targets}
    if joint:
        sb = sum(c * n for c, n in cb.values())
        sn = sum(c * n for c, n in cn.values())
        pick = {t.name: narrow.name if sn < sb else box.name for t in targets}
    else:
        pick = {t.name: narrow.name if cn[t.name][0] < cb[t.name][0] else box.name for t in targets}
    for t in targets:
        rec[t.name]["kernel"] = NARROW if pick[t.name] == narrow.name else 1.0
    return pick, rec
