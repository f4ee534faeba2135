"""The ChArUco board printed on the paper under the object: layout, albedo texture, world points, detection.

The board is an OpenCV ChArUco board (``cv2.aruco.CharucoBoard``, non-legacy pattern) whose centre block of
``blank_x`` x ``blank_y`` squares is left white: black squares are as dark as a dark object and would break its
silhouette and its shadows, so the object stands on plain paper and only the outer ring carries ink. Only the
ChArUco corners whose four surrounding squares are all printed are used (``valid_corner_ids``): a corner on the
edge of the blank block is no chessboard saddle and would be biased.

World frame (data_layout.md): the board is centred on the origin on the plane z = 0; OpenCV's board frame (origin
at the board's top-left outer corner, x along the columns, y down the rows, z into the paper) maps to world as
``(x - W/2, H/2 - y, 0)`` with W, H the board's size in metres, i.e. world +x along the board's columns, world +y
towards its first row. :func:`board_texture` places the image the same way under ``objcam.scene.make_plane``'s UV
convention (a square of ``extent`` metres centred on the origin, image row 0 towards +y, column 0 towards -x).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

PAPER_ALBEDO = 0.8
INK_ALBEDO = 0.05


class BoardSpec(BaseModel):
    """A ChArUco board with a white centre. Defaults: 13 x 9 squares of 30 mm (390 x 270 mm, an A3 sheet) with
    22 mm 4x4 markers and a blank centre of 7 x 5 squares (210 x 150 mm) for the object."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    squares_x: int = Field(13, ge=3, le=64, description="squares along the board's x (columns)")
    squares_y: int = Field(9, ge=3, le=64, description="squares along the board's y (rows)")
    square_length: float = Field(0.03, gt=0, description="chessboard square side, metres")
    marker_length: float = Field(0.022, gt=0, description="ArUco marker side, metres (< square_length)")
    dictionary: str = Field("DICT_4X4_100", description="cv2.aruco predefined dictionary name")
    blank_x: int = Field(7, ge=0, description="blank (white) centre squares along x; same parity as squares_x")
    blank_y: int = Field(5, ge=0, description="blank (white) centre squares along y; same parity as squares_y")
    margin: float = Field(0.01, ge=0, description="white paper around the board, metres (texture padding; "
                          "the default print is 410 x 290 mm, on A3)")

    @model_validator(mode="after")
    def _check(self):
        import cv2

        if self.marker_length >= self.square_length:
            raise ValueError("marker_length must be smaller than square_length")
        if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_100, DICT_5X5_250)")
        if (self.squares_x - self.blank_x) % 2 or (self.squares_y - self.blank_y) % 2:
            raise ValueError("blank_x/blank_y must have the parity of squares_x/squares_y (a centred blank block)")
        if self.blank_x > self.squares_x - 2 or self.blank_y > self.squares_y - 2:
            raise ValueError("the blank centre must leave a ring of at least one square")
        n_markers = (self.squares_x * self.squares_y) // 2
        dict_size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if n_markers > dict_size:
            raise ValueError(f"{self.dictionary} has {dict_size} markers; the board needs {n_markers}")
        if len(valid_corner_ids(self)) < 6:
            raise ValueError("the board's printed ring has fewer than 6 usable ChArUco corners")
        return self

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the board in metres (without the paper margin)."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    def blank_squares(self) -> tuple[range, range]:
        """(columns, rows) of the blank centre block."""
        c0 = (self.squares_x - self.blank_x) // 2
        r0 = (self.squares_y - self.blank_y) // 2
        return range(c0, c0 + self.blank_x), range(r0, r0 + self.blank_y)


def _key(spec: BoardSpec) -> str:
    return spec.model_dump_json()


@lru_cache(maxsize=8)
def _cv_board(key: str):
    import cv2

    spec = BoardSpec.model_validate_json(key)
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    board = cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_length, spec.marker_length, d)
    board.setLegacyPattern(False)
    return board


def cv_board(spec: BoardSpec):
    """The ``cv2.aruco.CharucoBoard`` of ``spec`` (the full board; the blank centre is a printing detail)."""
    return _cv_board(_key(spec))


def valid_corner_ids(spec: BoardSpec) -> np.ndarray:
    """Sorted ChArUco corner ids whose four surrounding squares are all printed (outside the blank centre).

    Corner id k sits at the inner intersection (column k % (squares_x - 1) + 1, row k // (squares_x - 1) + 1).
    """
    cols, rows = spec.blank_squares()
    nx = spec.squares_x - 1
    ids = []
    for k in range(nx * (spec.squares_y - 1)):
        i, j = k % nx, k // nx  # the corner touches squares (i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1)
        blank = any(c in cols and r in rows for c in (i, i + 1) for r in (j, j + 1))
        if not blank:
            ids.append(k)
    return np.asarray(ids, dtype=np.int64)


def board_points_world(spec: BoardSpec) -> dict[int, np.ndarray]:
    """ChArUco corner id -> its world position (x, y, 0) in metres, for the usable corners (valid_corner_ids)."""
    w, h = spec.size
    nx = spec.squares_x - 1
    out = {}
    for k in valid_corner_ids(spec):
        i, j = int(k) % nx, int(k) // nx
        out[int(k)] = np.array([(i + 1) * spec.square_length - w / 2, h / 2 - (j + 1) * spec.square_length, 0.0])
    return out


def world_points_array(spec: BoardSpec, ids: np.ndarray) -> np.ndarray:
    """(N, 3) world positions of corner ``ids`` (all must be valid)."""
    pts = board_points_world(spec)
    return np.array([pts[int(i)] for i in ids], dtype=np.float64).reshape(-1, 3)


class BoardTexture(NamedTuple):
    image: np.ndarray  # (N, N) float32 albedo, square
    extent: float  # side of the square it covers, metres (centred on the origin)
    px_per_m: float  # texels per metre (exact: a square is an even number of texels)


def board_texture(spec: BoardSpec, px_per_m: float = 4000.0) -> BoardTexture:
    """The printed sheet as a square albedo texture: paper PAPER_ALBEDO, ink INK_ALBEDO.

    The board is padded with paper (``spec.margin``, then to a square) and centred: used as the support texture of
    ``objcam.scene.make_plane(size, texture_extent=extent)`` it puts every ChArUco corner at
    ``board_points_world``. Square edges fall on texel boundaries (px_per_m is rounded so that a square is an
    even number of texels), so the chessboard corners are exact.
    """
    s = max(2, 2 * int(round(spec.square_length * px_per_m / 2)))  # texels per square, even
    ppm = s / spec.square_length
    bw, bh = spec.squares_x * s, spec.squares_y * s
    img = _draw_board(spec, s)
    cols, rows = spec.blank_squares()
    if spec.blank_x and spec.blank_y:
        img[rows.start * s : rows.stop * s, cols.start * s : cols.stop * s] = 255
    m = 2 * int(np.ceil(spec.margin * ppm / 2))
    n = max(bw, bh) + 2 * m  # even: bw, bh are multiples of an even s
    full = np.full((n, n), 255, dtype=np.uint8)
    r0, c0 = (n - bh) // 2, (n - bw) // 2
    full[r0 : r0 + bh, c0 : c0 + bw] = img
    alb = INK_ALBEDO + (PAPER_ALBEDO - INK_ALBEDO) * (full.astype(np.float32) / 255.0)
    return BoardTexture(alb.astype(np.float32), n / ppm, ppm)


def _draw_board(spec: BoardSpec, s: int) -> np.ndarray:
    """The full board (uint8, 0 ink / 255 paper) at ``s`` pixels per square: OpenCV's ChArUco layout (top-left
    square black, markers in the white squares in ``getIds`` order), drawn square by square so that every square
    edge is on a pixel boundary whatever ``s`` (``CharucoBoard.generateImage`` fails for some sizes)."""
    import cv2

    board = cv_board(spec)
    img = np.full((spec.squares_y * s, spec.squares_x * s), 255, dtype=np.uint8)
    for r in range(spec.squares_y):
        for c in range(spec.squares_x):
            if (r + c) % 2 == 0:
                img[r * s : (r + 1) * s, c * s : (c + 1) * s] = 0
    m = int(round(spec.marker_length / spec.square_length * s))
    d = board.getDictionary()
    for mid, corners in zip(np.ravel(board.getIds()), board.getObjPoints()):
        x0, y0 = np.asarray(corners, float)[0, :2] / spec.square_length  # in squares
        c, r = int(np.floor(x0)), int(np.floor(y0))
        if (r + c) % 2 == 0:
            raise RuntimeError("unexpected ChArUco layout: a marker on a black square")
        off = (s - m) // 2
        img[r * s + off : r * s + off + m, c * s + off : c * s + off + m] = cv2.aruco.generateImageMarker(
            d, int(mid), m, borderBits=1)
    return img


def write_board_texture(path: str | Path, spec: BoardSpec, px_per_m: float = 4000.0) -> float:
    """Write the board texture as an RGB EXR (a support albedo texture); returns its extent in metres."""
    from objcam.image_io import write_exr

    tex = board_texture(spec, px_per_m)
    write_exr(path, np.repeat(tex.image[..., None], 3, axis=2))
    return tex.extent


def write_board_print(path: str | Path, spec: BoardSpec, dpi: float = 300.0) -> None:
    """Write the board (with its paper margin) as a PNG to print at ``dpi`` (100% scale)."""
    from objcam.image_io import write_png

    tex = board_texture(spec, dpi / 0.0254)
    w, h = spec.size
    n = tex.image.shape[0]
    pw, ph = int(round((w + 2 * spec.margin) * tex.px_per_m)), int(round((h + 2 * spec.margin) * tex.px_per_m))
    r0, c0 = (n - ph) // 2, (n - pw) // 2
    img = (tex.image[r0 : r0 + ph, c0 : c0 + pw] - INK_ALBEDO) / (PAPER_ALBEDO - INK_ALBEDO)
    write_png(path, np.clip(img, 0, 1))


# --------------------------------------------------------------------------------------------------- detection


@lru_cache(maxsize=8)
def _detector(key: str):
    import cv2

    board = _cv_board(key)
    cp = cv2.aruco.CharucoParameters()
    cp.tryRefineMarkers = True
    dp = cv2.aruco.DetectorParameters()
    return cv2.aruco.CharucoDetector(board, cp, dp)


def to_gray8(image: np.ndarray) -> np.ndarray:
    """An 8-bit grey image from uint8/uint16 (H, W[, 3]) or float (display values in [0, 1]); RGB is averaged."""
    a = np.asarray(image)
    if a.ndim == 3:
        dt = a.dtype
        a = a[..., :3].astype(np.float64).mean(axis=2)
        if dt.kind in "ui":
            a = (a + 0.5).astype(dt)
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if a.dtype == np.uint16:
        return (a.astype(np.float64) / 257.0 + 0.5).astype(np.uint8)
    if a.dtype.kind in "ui":
        a = a.astype(np.float64) / max(1.0, float(a.max()))
    return (np.clip(np.nan_to_num(a.astype(np.float64)), 0, 1) * 255.0 + 0.5).astype(np.uint8)


def detect(image_gray: np.ndarray, spec: BoardSpec, refine: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """ChArUco corners of ``spec`` in an image.

    image_gray: (H, W) or (H, W, 3) uint8, uint16, or float display values in [0, 1] (tonemap HDR first).
    Returns (ids (N,) int64 sorted, corners (N, 2) float64 pixel (u, v) in the OpenCV convention: pixel centres
    at integers), only the usable corners (``valid_corner_ids``); empty arrays when the board is not found.
    refine: re-refine the corners in a window sized to the local square size (:func:`refine_corners`).
    """
    gray = to_gray8(image_gray)
    det = _detector(_key(spec))
    corners, ids, _, _ = det.detectBoard(gray)
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    ids = np.asarray(ids, dtype=np.int64).ravel()
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    keep = np.isin(ids, valid_corner_ids(spec))
    order = np.argsort(ids[keep], kind="stable")
    ids, corners = ids[keep][order], corners[keep][order]
    if refine and len(ids) > 1:
        corners = refine_corners(gray, corners, spec)
    return ids, corners


def refine_corners(gray: np.ndarray, corners: np.ndarray, spec: BoardSpec, max_half: int = 3) -> np.ndarray:
    """Re-refine small ChArUco corners with ``cv2.cornerSubPix`` in a window that stays inside the ink-free gap
    between the corner and the neighbouring markers (its size follows the local square size in pixels).

    OpenCV's own refinement window reaches the marker edges on small or oblique boards (measured on 32 spp
    renders: 0.26 px mean error on ~15 px squares at 320 x 240, 0.14 px with this window); on larger squares
    (window half-size above ``max_half``) OpenCV's corner is kept (there it was better: 0.096 vs 0.107 px at
    800 x 600).
    """
    import cv2

    c = np.asarray(corners, dtype=np.float64)
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    np.fill_diagonal(d, np.inf)
    # nearest other corner ~ one (foreshortened) square; the gap to a marker is (L - M) / 2 of it
    gap = d.min(axis=1) * (spec.square_length - spec.marker_length) / (2 * spec.square_length)
    half = np.clip(np.floor(1.1 * gap), 2, 12).astype(int)
    out = c.copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    for w in np.unique(half[half <= max_half]):
        sel = half == w
        pts = c[sel].astype(np.float32).reshape(-1, 1, 2).copy()
        out[sel] = cv2.cornerSubPix(gray, pts, (int(w), int(w)), (-1, -1), crit).reshape(-1, 2)
    moved = np.linalg.norm(out - c, axis=1) > 2.0  # a refinement that ran off: keep OpenCV's corner
    out[moved] = c[moved]
    return out


def detect_file(path: str | Path, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """:func:`detect` on an image file (8/16-bit PNG, JPEG, TIFF; EXR/HDR are tonemapped first)."""
    return detect(read_display_image(path), spec)


def read_display_image(path: str | Path) -> np.ndarray:
    """An image file as display values: uint8/uint16 as stored, EXR (linear HDR) tonemapped to [0, 1] float."""
    import cv2

    from objcam.errors import InputError

    path = Path(path)
    if path.suffix.lower() in (".exr", ".hdr"):
        from objcam.image_io import read_exr, tonemap

        return tonemap(read_exr(path)[..., :3])[0].astype(np.float32)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("image does not read", path, "give an 8/16-bit PNG, JPEG or TIFF, or a linear EXR")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1]
    return img
