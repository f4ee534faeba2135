"""A graded summary of the capture front end (green / yellow / red per check, with the fix for what is not green),
in the spirit of nerfstudio's / COLMAP's capture reports."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

Grade = Literal["green", "yellow", "red"]
_ORDER = {"green": 0, "yellow": 1, "red": 2}


class Check(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    grade: Grade
    value: str  # the measured value, short ("22/24 views", "0.41 px")
    detail: str = ""
    fix: str | None = None  # what to do (yellow and red)


def worst(checks: list[Check]) -> Grade:
    return max((c.grade for c in checks), key=_ORDER.__getitem__, default="green")


def _grade(value: float, green: float, yellow: float) -> Grade:
    """Lower is better: green below ``green``, yellow below ``yellow``, else red (NaN is red)."""
    if value == value and value < green:
        return "green"
    if value == value and value < yellow:
        return "yellow"
    return "red"


def grade_checks(*, n_views: int, views_registered: int, targets: list[str], targets_registered: list[str],
                 mean_reprojection_px: float, views_with_board: int, board_corner_rms_mm: float,
                 board_plane_rms_mm: float, board_reprojection_px: float | None,
                 target_pnp: dict[str, dict] | None = None, board_square_mm: float = 30.0,
                 probes: list[str] | None = None, probes_registered: list[str] | None = None,
                 probe_pnp: dict[str, dict] | None = None) -> list[Check]:
    """The checks of one front-end run (see :func:`objcam.sfm.frontend.estimate_cameras`)."""
    checks: list[Check] = []
    frac = views_registered / max(1, n_views)
    g: Grade = "green" if views_registered == n_views else ("yellow" if frac >= 0.8 else "red")
    checks.append(Check(name="views registered", grade=g, value=f"{views_registered}/{n_views} views",
                        fix=None if g == "green" else
                        f"only {views_registered}/{n_views} views registered: add views with more overlap "
                        "(neighbouring views 10-20 degrees apart), sharp, with the board and object in frame"))
    missing = [t for t in targets if t not in targets_registered]
    if targets:
        checks.append(Check(name="targets registered", grade="red" if missing else "green",
                            value=f"{len(targets) - len(missing)}/{len(targets)} targets",
                            detail=("not registered: " + ", ".join(missing)) if missing else "",
                            fix=None if not missing else
                            "shoot the target from near the ring of views, with the board in frame, or add views "
                            "between the ring and the target"))
    missing_p = [p for p in probes or [] if p not in (probes_registered or [])]
    if probes:
        checks.append(Check(name="probes registered", grade="red" if missing_p else "green",
                            value=f"{len(probes) - len(missing_p)}/{len(probes)} chrome-ball photos",
                            detail=("not registered: " + ", ".join(missing_p)) if missing_p else "",
                            fix=None if not missing_p else
                            "shoot the chrome ball from the target's tripod position with the board's ring in "
                            "frame, or give the probe's camera in capture.toml"))
    g = _grade(mean_reprojection_px, 0.7, 1.5)
    checks.append(Check(name="SfM reprojection error", grade=g, value=f"{mean_reprojection_px:.2f} px",
                        fix=None if g == "green" else "blurred or shifted photos: use a tripod or a faster shutter, "
                        "keep the object and the sheet still, switch off lens stabilisation on a tripod"))
    bfrac = views_with_board / max(1, views_registered)
    g = "green" if bfrac >= 0.8 else ("yellow" if bfrac >= 0.5 else "red")
    checks.append(Check(name="board found", grade=g, value=f"{views_with_board}/{views_registered} views",
                        fix=None if g == "green" else "keep the printed ring of the board in frame and in focus "
                        "in every view; light it evenly (no glare on the paper)"))
    g = _grade(board_corner_rms_mm, 1.0, 3.0)
    checks.append(Check(name="board residual", grade=g, value=f"{board_corner_rms_mm:.2f} mm RMS",
                        detail="triangulated board corners vs the board layout after the similarity fit",
                        fix=None if g == "green" else
                        f"measure a printed square: it must be {board_square_mm:g} mm (print at 100% scale, "
                        "or set square_length to what you measure); the paper must lie flat"))
    g = _grade(board_plane_rms_mm, 1.0, 3.0)
    checks.append(Check(name="board flatness", grade=g, value=f"{board_plane_rms_mm:.2f} mm RMS",
                        detail="triangulated board corners off the plane z = 0",
                        fix=None if g == "green" else "the sheet is not flat: tape it down on a flat table"))
    if board_reprojection_px is not None:
        g = _grade(board_reprojection_px, 0.5, 1.0)
        checks.append(Check(name="board reprojection", grade=g, value=f"{board_reprojection_px:.2f} px RMS",
                            detail="board corners through the final cameras",
                            fix=None if g == "green" else "board corners do not fit the cameras: blur, a warped "
                            "print, or board settings that do not match the print"))
    for label, name, r in [("target", n, r) for n, r in (target_pnp or {}).items()] + \
            [("probe", n, r) for n, r in (probe_pnp or {}).items()]:
        d, a = r["centre_mm"], r["rotation_deg"]
        g = "green" if (d < 2.0 and a < 0.2) else ("yellow" if (d < 10.0 and a < 1.0) else "red")
        checks.append(Check(name=f"{label} {name} pose", grade=g, value=f"{d:.2f} mm, {a:.3f} deg",
                            detail="board-only PnP vs the final pose",
                            fix=None if g == "green" else "keep more of the board (its whole ring) in the target "
                            "view, in focus"))
    return checks


def format_checks(checks: list[Check], color: bool = False) -> str:
    """One line per check: ``[green] views registered: 24/24 views`` (+ `` -- fix: ...``)."""
    codes = {"green": "\033[32m", "yellow": "\033[33m", "red": "\033[31m"}
    lines = []
    for c in checks:
        tag = f"{codes[c.grade]}{c.grade:>6}\033[0m" if color else f"{c.grade:>6}"
        line = f"[{tag}] {c.name}: {c.value}"
        if c.detail and c.grade != "green":
            line += f" ({c.detail})"
        if c.fix:
            line += f" -- fix: {c.fix}"
        lines.append(line)
    return "\n".join(lines)
