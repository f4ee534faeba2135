"""The report's sections on how a photographed capture became a scene: ingest (brackets, merged HDR,
saturation), SfM (grade, registered views, reprojection error, camera positions around the board), geometry
(silhouettes over photos, registration residuals), texture (the albedo maps) and probe (ball fit, unwrapped map).
Each reads its stage's folder (``up[stage]``); a stage that did not run gets no section."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from objcam.report import html as H


def _json(path: Path) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


THUMB = 480  # pixels: the sections' figures sit in a grid of ~360 px columns


def _fit(png: bytes | None, width: int = THUMB) -> bytes | None:
    """PNG bytes no wider than ``width`` (area-averaged): these are context, the envmap is the result."""
    import cv2

    if png is None:
        return None
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.shape[1] <= width:
        return png
    img = cv2.resize(img, (width, max(1, round(img.shape[0] * width / img.shape[1]))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return buf.tobytes() if ok else png


def _png_bytes(display: np.ndarray) -> bytes:
    """PNG bytes of display values (H, W[, 3]) in [0, 1]."""
    import cv2

    img = (np.clip(display, 0, 1) * 255 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", img[..., ::-1] if img.ndim == 3 else img)
    return buf.tobytes() if ok else None


def _exr_png(path: Path, gamma_only: bool = False) -> bytes | None:
    """A linear EXR as a PNG: tonemapped (99th percentile, gamma 2.2) or, for albedo, gamma 2.2 alone."""
    from objcam.image_io import read_exr, tonemap

    if not Path(path).is_file():
        return None
    img = read_exr(path)[..., :3]
    return _png_bytes(np.clip(img, 0, 1) ** (1 / 2.2) if gamma_only else tonemap(img)[0])


def _stage_lead(up: dict[str, Path], stage: str, keys: tuple[str, ...] = ()) -> str:
    rec = _json(up[stage] / "stage.json") or {}
    m = rec.get("metrics") or {}
    parts = [f'<p>{H.esc(rec.get("summary") or "")}</p>']
    rows = [(k, m[k]) for k in keys if k in m and not isinstance(m[k], (dict, list))]
    if rows:
        parts.append(H.table(("measure", "value"), rows))
    return "".join(parts)


def _white(png: bytes | None) -> str:
    """A mask's share of white pixels for its caption (", 99.8% of the image"): an all-white mask shows as a blank
    panel, and the number says that it is one."""
    import cv2

    img = None if png is None else cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    return "" if img is None or img.size == 0 else f", {np.mean(img > 127):.1%} of the image"


def _ingest(up: dict[str, Path], width: int, capture: Path | None = None) -> str:
    d = up["ingest"]
    parts = [_stage_lead(up, "ingest", ("views", "targets", "probes", "photos", "white_balance_source", "units"))]
    rows, figs = [], []
    for kind in ("targets", "probes"):
        for m in sorted((d / kind).glob("*/merge.json")):
            j = _json(m) or {}
            times = j.get("exposure_times_s") or []
            rows.append((f"{kind[:-1]} {m.parent.name}", len(j.get("frames") or []),
                         f"{min(times):.4g} .. {max(times):.4g} s" if times else "\u2014",
                         j.get("saturated_fraction"), j.get("reader")))
            figs.append(H.figure(_fit(_exr_png(m.parent / "image.exr")), f"{kind[:-1]} {m.parent.name}: merged HDR "
                                 "(99th percentile, gamma 1/2.2)"))
            valid = H.read_png(m.parent / "valid.png")
            figs.append(H.figure(_fit(valid), f"{kind[:-1]} {m.parent.name}: usable pixels (white{_white(valid)}; "
                                 "black: saturated in every frame or outside the merge's range)"))
    if rows:
        parts.append(H.table(("bracket", "frames", "exposure times", "saturated in every frame", "reader"), rows))
    parts.append(H.grid(figs))
    return "".join(parts)


def _camera_positions_png(d: Path, board: tuple[float, float] | None = None) -> bytes | None:
    """Top view of the posed cameras around the board (``board``: its (width, height) in metres, centred on the
    origin): views (dots, with their viewing direction), targets and probes (stars), the origin (the object's
    foot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from objcam.camera import Camera

    fig = Figure(figsize=(5.5, 5.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    any_cam = False
    for kind, style in (("views", dict(marker="o", color="C0", s=18)), ("targets", dict(marker="*", color="C3", s=120)),
                        ("probes", dict(marker="P", color="C2", s=60))):
        cams = [Camera.model_validate_json(p.read_text()) for p in sorted((d / "cameras" / kind).glob("*.json"))]
        if not cams:
            continue
        any_cam = True
        m = np.array([np.asarray(c.world_from_camera) for c in cams])
        c, fwd = m[:, :3, 3], m[:, :3, 2]
        ax.scatter(c[:, 0], c[:, 1], label=f"{kind} ({len(cams)})", zorder=3, **style)
        span = float(np.ptp(c[:, :2])) or 1.0
        ax.quiver(c[:, 0], c[:, 1], fwd[:, 0], fwd[:, 1], angles="xy", scale_units="xy", scale=8 / span,
                  color=style["color"], width=0.004, alpha=0.6)
    if not any_cam:
        return None
    ax.scatter([0], [0], marker="+", color="black", s=80, label="origin (object)")
    if board is not None:
        from matplotlib.patches import Rectangle

        bw, bh = board
        ax.add_patch(Rectangle((-bw / 2, -bh / 2), bw, bh, fill=False, color="0.3", lw=1.2, label="board"))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title("cameras seen from above (arrows: viewing direction)", fontsize=9)
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _board_size(capture: Path | None) -> tuple[float, float] | None:
    from objcam.schemas.capture import try_load

    m = try_load(capture) if capture is not None else None
    return m.board.size if m is not None and m.board is not None else None


def _sfm(up: dict[str, Path], width: int, capture: Path | None = None) -> str:
    keys = ("grade", "registered", "images", "views_registered", "mean_reprojection_px", "board_corner_rms_mm",
            "board_reprojection_px", "n_points", "shared_camera")
    png = _camera_positions_png(up["sfm"], _board_size(capture))
    return _stage_lead(up, "sfm", keys) + H.grid([H.figure(png, "camera positions around the board", plot=True,
                                                          missing="no posed cameras")])


def _silhouette_overlay(view_png: Path, mask_png: Path) -> bytes | None:
    """The view with the silhouette mask over it: object red, no evidence grey, background as is."""
    import cv2

    photo, mask = cv2.imread(str(view_png), cv2.IMREAD_COLOR), cv2.imread(str(mask_png), cv2.IMREAD_UNCHANGED)
    if photo is None or mask is None:
        return None
    if mask.shape[:2] != photo.shape[:2]:
        mask = cv2.resize(mask, (photo.shape[1], photo.shape[0]), interpolation=cv2.INTER_NEAREST)
    out = photo.astype(np.float64) / 255.0
    obj, unk = mask > 200, (mask > 60) & (mask <= 200)
    out[obj] = 0.5 * out[obj] + 0.5 * np.array([0.0, 0.0, 1.0])  # BGR red
    out[unk] = 0.5 * out[unk] + 0.25
    ok, buf = cv2.imencode(".png", (out * 255 + 0.5).astype(np.uint8))
    return buf.tobytes() if ok else None


def _geometry(up: dict[str, Path], width: int, capture: Path | None = None) -> str:
    d = up["geometry"]
    g = _json(d / "geometry.json") or {}
    reg = g.get("registration") or {}
    rows = [(k, v) for k, v in (("object source", g.get("object_source")), ("object faces", g.get("object_faces")),
                                ("object height (mm)", g.get("object_height_mm")),
                                ("registration residual to the hull (mm RMS)", reg.get("rms_mm")),
                                ("plane RMS (mm)", (g.get("plane") or {}).get("rms_mm")),
                                ("hull volume (cm^3)", g.get("hull_volume_cm3"))) if v is not None]
    parts = [_stage_lead(up, "geometry"), H.table(("measure", "value"), rows) if rows else ""]
    masks = sorted((d / "masks").glob("*.png"))
    step = max(1, len(masks) // 4)
    figs = [H.figure(_fit(_silhouette_overlay(up["ingest"] / "views" / m.name, m)), f"silhouette over view {m.stem} "
                     "(red: object, grey: no evidence)") for m in masks[::step][:4]] if "ingest" in up else []
    parts.append(H.grid(figs))
    return "".join(parts)


def _texture(up: dict[str, Path], width: int, capture: Path | None = None) -> str:
    d = up["texture"]
    figs = [H.figure(_fit(_exr_png(d / f"albedo_{w}.exr", gamma_only=True)), f"{w} albedo over its UV atlas (linear, "
                     "gamma 1/2.2)", missing=f"no albedo_{w}.exr") for w in ("object", "support")]
    return _stage_lead(up, "texture", ("object_texels_seen", "support_extent_m", "median_samples_object")) + \
        H.grid(figs)


def _probe(up: dict[str, Path], width: int, capture: Path | None = None) -> str:
    d = up["probe"]
    figs = []
    for folder in sorted(p for p in d.iterdir() if p.is_dir()):
        figs.append(H.figure(_fit(H.read_png(folder / "ball.png")), f"probe {folder.name}: the ball and its fitted "
                             "outline (green)"))
        figs.append(H.figure(_fit(H.read_png(folder / "envmap_gt.png")), f"probe {folder.name}: unwrapped map "
                             "(standard lat-long; invalid texels dimmed)"))
    return _stage_lead(up, "probe") + H.grid(figs)


SECTIONS = (("ingest", "Ingest: photos to linear HDR", _ingest), ("sfm", "Structure from motion", _sfm),
            ("geometry", "Geometry", _geometry), ("texture", "Texture", _texture),
            ("probe", "Chrome-ball probe", _probe))


def capture_sections(up: dict[str, Path], width: int, capture: Path | None = None) -> tuple[str, list[tuple[str, str]]]:
    """HTML of every photo stage that ran, and (id, title) of each for the page's table of contents."""
    html, toc = [], []
    for stage, title, build in SECTIONS:
        if stage not in up or not (up[stage] / "stage.json").is_file():
            continue
        html.append(f'<section id="{stage}"><h2>{H.esc(title)}</h2>{build(up, width, capture)}</section>')
        toc.append((stage, title))
    return "".join(html), toc
