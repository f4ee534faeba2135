"""On-disk transport matrices: one zarr v3 group per distinct camera, and ``index.json`` naming each target's.

Transport artifact folder (``objcam/transport/``):
    index.json      {"format": 1, "targets": {target name: group folder}, "groups": {group folder: [names]}}
    cam0/           zarr v3 group (``zarr.json`` inside), one per distinct camera:
        A               float32 (C, M, N), chunks (C, <= 32768 rows, 128 columns): column blocks can be computed
                        and written independently. C = 1 when every albedo is grey (A holds the albedo), else 3
                        (A_c = diag(rho_c) A' for direct light).
        pixel_index     int64 (M,)   flat row * W' + col into the pooled (H', W') target image
        texel_index     int64 (N,)   flat r * W_env + c into the (env_height, 2 env_height) envmap
        directions      float32 (N, 3) texel centre directions (world, z up)
        solid_angle     float32 (N,)  steradians
        albedo          float32 (M, 3) albedo rendered, mean over the pixel's samples that hit a surface
        unknown_albedo  bool (M,)    a sample of the pixel lands on a surface of unknown albedo (rendered as 1)
        coverage        float32 (M,)  fraction of the pixel's samples that hit a surface (the rest see the envmap)
        object_fraction float32 (M,)  fraction of the hitting samples that land on the object
        attributes: image_shape, downsample, env_height (A's grid), output_height (the envmap the solve writes:
                    env_height, or env_height / transport.supersample), channels, model, samples, spp, max_depth,
                    camera, targets, metrics
Units: x is envmap radiance per texel (box texels); A x is pixel radiance.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.envmap import EnvGrid

FORMAT = 1
INDEX = "index.json"
GRAM = "gram.npy"  # (C, N, N) float64 A_c^T A_c, so solves skip the O(M N^2) product
BOUNCE = "bounce.npz"  # the node gather's parts (objcam.transport.gather.bounce_parts), when A has them
ROW_CHUNK = 32768

_META_ARRAYS = ("pixel_index", "texel_index", "directions", "solid_angle", "albedo", "unknown_albedo", "coverage",
                "object_fraction")


def _compressor():
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="lz4", clevel=1, shuffle="shuffle")


class ColumnWriter:
    """Streams kept columns of A into a zarr group, buffering whole column chunks.

    The array is created with the largest possible width and shrunk by :meth:`finish`.
    """

    def __init__(self, folder: str | Path, channels: int, n_pixels: int, n_texels_max: int, chunk_columns: int = 128):
        import zarr

        self.folder = Path(folder)
        self.group = zarr.open_group(str(self.folder), mode="w", zarr_format=3)
        self.c, self.m = int(channels), int(n_pixels)
        self.chunk = int(chunk_columns)
        self.A = self.group.create_array("A", shape=(self.c, self.m, max(1, n_texels_max)), dtype="float32",
                                         chunks=(self.c, max(1, min(self.m, ROW_CHUNK)), self.chunk),
                                         compressors=_compressor(), fill_value=0.0)
        self._buf: list[np.ndarray] = []
        self._buf_n = 0
        self.texels: list[np.ndarray] = []
        self.norms: list[np.ndarray] = []
        self.n = 0  # columns written

    def append(self, texels: np.ndarray, cols: np.ndarray) -> None:
        """Add columns (C, M, B) for flat texel indices ``texels`` (B,)."""
        if cols.shape[2] == 0:
            return
        self.texels.append(np.asarray(texels, dtype=np.int64))
        self.norms.append(np.sqrt(np.einsum("cmb,cmb->b", cols, cols, dtype=np.float64)))
        self._buf.append(np.asarray(cols, dtype=np.float32))
        self._buf_n += cols.shape[2]
        if self._buf_n >= self.chunk:
            self._flush(final=False)

    def _flush(self, final: bool) -> None:
        if not self._buf:
            return
        data = np.concatenate(self._buf, axis=2)
        n_out = data.shape[2] if final else (data.shape[2] // self.chunk) * self.chunk
        if n_out:
            self.A[:, :, self.n : self.n + n_out] = data[:, :, :n_out]
            self.n += n_out
        rest = data[:, :, n_out:]
        self._buf = [rest] if rest.shape[2] else []
        self._buf_n = rest.shape[2]

    def flush(self) -> None:
        """Write every buffered column and shrink A to the columns written (no appends after this)."""
        self._flush(final=True)
        self.A.resize((self.c, self.m, self.n))

    def finish(self, arrays: dict[str, np.ndarray], attrs: dict) -> None:
        """Flush, then write the metadata arrays and the group's attributes."""
        self.flush()
        for name, arr in arrays.items():
            arr = np.ascontiguousarray(arr)
            chunks = tuple(max(1, n) for n in arr.shape) or None
            a = self.group.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=chunks,
                                        compressors=_compressor())
            a[...] = arr
        self.group.attrs.update(attrs)

    @property
    def texel_index(self) -> np.ndarray:
        return np.concatenate(self.texels) if self.texels else np.zeros(0, np.int64)

    @property
    def column_norms(self) -> np.ndarray:
        return np.concatenate(self.norms) if self.norms else np.zeros(0)


def add_to_columns(folder: str | Path, delta_fn, chunk_columns: int | None = None, progress=None) -> None:
    """In place: A[:, :, a:b] += delta_fn(a, b) (C, M, b - a), one column chunk at a time."""
    import zarr

    g = zarr.open_group(str(folder), mode="r+")
    A = g["A"]
    n = A.shape[2]
    step = chunk_columns or A.chunks[2]
    for a in range(0, n, step):
        b = min(n, a + step)
        A[:, :, a:b] = A[:, :, a:b] + delta_fn(a, b).astype(np.float32)
        if progress is not None:
            progress.update(b - a)


def write_columns(src: str | Path, dst: str | Path, pos: np.ndarray, cols: np.ndarray, gram: np.ndarray,
                  attrs: dict | None = None) -> None:
    """A group ``dst``: the group ``src`` with A's columns ``pos`` (B,) replaced by ``cols`` (C, M, B) and its
    Gram matrix ``gram`` (C, N, N) (objcam.transport.kernel's compact kernel and point sources), ``attrs`` added
    to its attributes. The stage's folder is temporary until it finishes, so the copy needs no atomic step of its
    own; gram.npy is written as write_gram writes it."""
    import shutil

    import zarr

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(GRAM))
    g = zarr.open_group(str(dst), mode="r+")
    arr = g["A"]
    step = arr.chunks[2]
    pos = np.asarray(pos, np.int64)
    for a in sorted({int(p) // step * step for p in pos}):
        b = min(arr.shape[2], a + step)
        chunk = arr[:, :, a:b]
        sel = np.flatnonzero((pos >= a) & (pos < b))
        chunk[:, :, pos[sel] - a] = cols[:, :, sel]
        arr[:, :, a:b] = chunk
    g.attrs["narrow_texels"] = [int(t) for t in np.asarray(g["texel_index"][...])[pos]]
    g.attrs.update(attrs or {})
    _save_gram(dst, gram.shape[0], gram.shape[1], iter(gram))


def write_index(out: str | Path, mapping: dict[str, str]) -> None:
    from objcam.image_io import atomic_write_text

    groups: dict[str, list[str]] = {}
    for name, folder in mapping.items():
        groups.setdefault(folder, []).append(name)
    atomic_write_text(Path(out) / INDEX, json.dumps({"format": FORMAT, "targets": mapping, "groups": groups},
                                                    indent=2))


def read_index(folder: str | Path) -> dict:
    from objcam.errors import StageError

    path = Path(folder) / INDEX
    if not path.is_file():
        raise StageError("transport artifact has no index.json", path, "rerun the transport stage")
    return json.loads(path.read_text())


@dataclass
class Transport:
    """A transport matrix and what its rows and columns mean (see the module docstring)."""

    A: np.ndarray  # (C, M, N) float32
    pixel_index: np.ndarray  # (M,)
    image_shape: tuple[int, int]  # pooled (H', W')
    downsample: int
    texel_index: np.ndarray  # (N,)
    env_height: int
    directions: np.ndarray  # (N, 3)
    solid_angle: np.ndarray  # (N,)
    albedo: np.ndarray  # (M, 3)
    unknown_albedo: np.ndarray  # (M,) bool
    coverage: np.ndarray  # (M,)
    object_fraction: np.ndarray  # (M,)
    model: str
    samples: int | None
    spp: int | None
    max_depth: int | None
    camera: Camera
    attrs: dict = field(default_factory=dict)
    folder: Path | None = None  # the zarr group this A was read from (identifies A across targets)
    _gram: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)  # gram.npy, read once

    @property
    def channels(self) -> int:
        return self.A.shape[0]

    @property
    def n_pixels(self) -> int:
        return self.A.shape[1]

    @property
    def n_texels(self) -> int:
        return self.A.shape[2]

    @property
    def grid(self) -> EnvGrid:
        return EnvGrid(self.env_height)

    @property
    def output_height(self) -> int:
        """Rows of the envmap the solve writes: env_height, or fewer when A was supersampled
        (transport.supersample; objcam.solvers.refine)."""
        return int(self.attrs.get("output_height") or self.env_height)

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Pooled image (H', W', 3) of A x for x (N, 3) (or (N,): grey), zeros where no pixel is kept."""
        y = self.predict_pixels(x)
        img = np.zeros((self.image_shape[0] * self.image_shape[1], 3), np.float32)
        img[self.pixel_index] = y
        return img.reshape(self.image_shape[0], self.image_shape[1], 3)

    def predict_pixels(self, x: np.ndarray) -> np.ndarray:
        """(M, 3) A x at the kept pixels."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim == 1:
            x = np.repeat(x[:, None], 3, axis=1)
        if x.shape != (self.n_texels, 3):
            raise ValueError(f"x must be ({self.n_texels}, 3), got {x.shape}")
        if self.channels == 1:
            return self.A[0] @ x
        return np.stack([self.A[c] @ x[:, c] for c in range(3)], axis=1)

    def x_from_envmap(self, env: np.ndarray) -> np.ndarray:
        """(N, 3) kept texels of an envmap (env_height, 2 env_height, 3) in this grid."""
        e = np.asarray(env).reshape(self.grid.n_texels, -1)
        return e[self.texel_index].astype(np.float32)

    def envmap_from_x(self, x: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(env_height, 2 env_height, 3) envmap holding x at the kept texels and ``fill`` elsewhere."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim == 1:
            x = np.repeat(x[:, None], 3, axis=1)
        env = np.full((self.grid.n_texels, 3), fill, np.float32)
        env[self.texel_index] = x
        return env.reshape(self.env_height, 2 * self.env_height, 3)

    def pixels_of(self, image: np.ndarray) -> np.ndarray:
        """(M, C') values of a pooled image (H', W', C') at the kept pixels."""
        img = np.asarray(image)
        return img.reshape(self.image_shape[0] * self.image_shape[1], -1)[self.pixel_index]

    def kept_mask(self) -> np.ndarray:
        """(H', W') True at the kept pixels."""
        m = np.zeros(self.image_shape[0] * self.image_shape[1], bool)
        m[self.pixel_index] = True
        return m.reshape(self.image_shape)

    def gram(self) -> np.ndarray:
        """(C, N, N) float64 A_c^T A_c over all kept pixels: read from ``gram.npy`` (written by the transport
        stage, so a solve costs no O(M N^2) work), computed when absent. The file is read once and kept,
        read-only and memory-mapped (a solve asks for it several times: 3 reads of 140 MB at 64 x 128)."""
        if self._gram is not None:
            return self._gram
        if self.folder is not None and (self.folder / GRAM).is_file():
            # memory-mapped, read-only: its pages are the file's cached pages (no private copy: 2.2 GB per
            # channel at 128 x 256), read on demand and given back when the memory is needed
            self._gram = np.load(self.folder / GRAM, mmap_mode="r")
            return self._gram
        from objcam.solvers import gram

        return np.stack([gram(self.A[c]) for c in range(self.channels)])

    @property
    def has_bounce_parts(self) -> bool:
        """Whether :meth:`bounce_parts` has something to load (without loading it)."""
        return self.folder is not None and (self.folder / BOUNCE).is_file()

    def bounce_parts(self) -> dict | None:
        """The interreflection gather's parts (objcam.transport.gather.GatherIndirect.bounce_parts), so a later
        albedo estimate can redo the light the support throws (:func:`objcam.transport.gather.bounce_delta`);
        None when A has none (direct light, the path-traced correction, or every albedo known)."""
        if not self.has_bounce_parts:
            return None
        with np.load(self.folder / BOUNCE) as z:
            return {k: z[k] for k in z.files}

    def rho_free(self, rows: np.ndarray | None = None) -> np.ndarray:
        """A' = A / rho per pixel and channel where rho > 0 (0 elsewhere), shape (C, M, N); with ``rows``
        only those pixels (C, len(rows), N), without a copy of the whole A first."""
        rho = self.albedo.T[: self.channels] if self.channels == 3 else self.albedo.mean(axis=1)[None]
        inv = np.where(rho > 0, 1.0 / np.maximum(rho, 1e-30), 0.0).astype(np.float32)
        if rows is None:
            return self.A * inv[:, :, None]
        rows = np.asarray(rows)
        rows = np.flatnonzero(rows) if rows.dtype == bool else rows
        out = np.empty((inv.shape[0], rows.size, self.A.shape[2]), np.float32)
        for c in range(inv.shape[0]):
            np.take(self.A[c], rows, axis=0, out=out[c])
            out[c] *= inv[c][rows][:, None]
        return out


def write_gram(folder: str | Path) -> float:
    """Store A_c^T A_c (C, N, N) float64 beside A as ``gram.npy``; returns the seconds it took.

    Each channel's Gram matrix is computed into one N x N array and streamed to the file (:func:`_save_gram`):
    the peak beside A is one Gram matrix (2.2 GB at 128 x 256), not the stacked channels and their serialised
    copies."""
    import time

    from objcam.solvers import gram
    from objcam.threads import blas_threads

    t0 = time.perf_counter()
    tr = load_group(folder)
    G = np.empty((tr.n_texels, tr.n_texels), np.float64)

    def channels():
        # one large float64 syrk per channel: two threads take it 0.84 -> 0.36 s at 16,384 x 1,088 on 2 cores
        # (objcam.threads: it is factorisations and line searches, not big products, that one thread protects)
        with blas_threads():
            for ch in range(tr.channels):
                yield gram(tr.A[ch], out=G)

    _save_gram(folder, tr.channels, tr.n_texels, channels())
    return time.perf_counter() - t0


def _save_gram(folder: str | Path, c: int, n: int, channels) -> None:
    """Write ``gram.npy`` (C, N, N) float64 into ``folder`` from ``channels``, an iterable of the C (N, N)
    float64 matrices in order, streamed to a temporary file renamed into place (atomic)."""
    import os

    from objcam.image_io import _tmp_path

    path = Path(folder) / GRAM
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            np.lib.format.write_array_header_1_0(f, {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float64)),
                                                     "fortran_order": False, "shape": (c, n, n)})
            for G in channels:
                np.ascontiguousarray(G, np.float64).tofile(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def load_group(folder: str | Path, load_A: bool = True) -> Transport:
    """A Transport from one zarr group folder."""
    import zarr

    g = zarr.open_group(str(folder), mode="r")
    at = dict(g.attrs)
    arrays = {n: np.asarray(g[n][...]) for n in _META_ARRAYS}
    A = np.asarray(g["A"][...]) if load_A else np.zeros((int(at["channels"]), 0, 0), np.float32)
    return Transport(A=A, image_shape=tuple(at["image_shape"]), downsample=int(at["downsample"]),
                     env_height=int(at["env_height"]), model=str(at["model"]), samples=at.get("samples"),
                     spp=at.get("spp"), max_depth=at.get("max_depth"), camera=Camera.model_validate(at["camera"]),
                     attrs=at, folder=Path(folder), **arrays)


def load_transport(folder: str | Path, target_name: str, load_A: bool = True) -> Transport:
    """The transport matrix of target ``target_name`` from a transport artifact folder (A loaded fully)."""
    from objcam.errors import StageError

    index = read_index(folder)
    sub = index["targets"].get(target_name)
    if sub is None:
        raise StageError(f"no transport matrix for target {target_name!r} (have {sorted(index['targets'])})",
                         Path(folder) / INDEX, "rerun the transport stage after changing the targets")
    return load_group(Path(folder) / sub, load_A=load_A)


def write_bounce(folder: str | Path, parts: dict) -> None:
    """Store the gather's parts beside A as ``bounce.npz`` (atomically)."""
    import io

    from objcam.image_io import atomic_write_bytes

    buf = io.BytesIO()
    np.savez(buf, **parts)
    atomic_write_bytes(Path(folder) / BOUNCE, buf.getvalue())
