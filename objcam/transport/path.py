"""Path-traced columns of A: one Mitsuba render per texel (or texel group) with that texel alone lit.

The scene is built once; each column swaps the envmap emitter's data for a one-hot box envmap
(:func:`objcam.render.mitsuba_box_bitmap`), so the BVH is kept and the render kernel is reused.
"""

from __future__ import annotations

import numpy as np

from objcam.camera import Camera
from objcam.dr_memory import padded
from objcam.envmap import to_mitsuba_bitmap
from objcam.scene import use_mitsuba
from objcam.transport.geometry import SceneGeometry


def scaled_camera(camera: Camera, f: int) -> Camera:
    """The camera whose pixel (U, V) is the f x f block of ``camera``'s pixels f U .. f U + f - 1 (same pose)."""
    if f == 1:
        return camera
    return Camera(width=camera.width // f, height=camera.height // f, fx=camera.fx / f, fy=camera.fy / f,
                  cx=(camera.cx + 0.5) / f - 0.5, cy=(camera.cy + 0.5) / f - 0.5,
                  world_from_camera=camera.world_from_camera)


class PathRenderer:
    """Renders columns of A (pooled pixels ``pixel_index`` of ``camera`` pooled by ``f``) with Mitsuba's path
    integrator: box pixel filter over the whole pooled footprint, ``spp`` samples per pooled pixel."""

    def __init__(self, geo: SceneGeometry, camera: Camera, f: int, pixel_index: np.ndarray, env_height: int,
                 upsample: int | None = None):
        self.geo = geo
        self.camera = camera
        self.f = int(f)
        self.pooled = scaled_camera(camera, self.f)
        self.pixel_index = np.asarray(pixel_index, dtype=np.int64)
        self.env_height = int(env_height)
        self.upsample = int(upsample if upsample is not None else geo.upsample)
        self._params = None
        self.renders = 0
        self.column_offset = 0
        self.column_offset = self._measure_column_offset()

    def _measure_column_offset(self) -> int:
        """Columns by which Mitsuba's envmap sits rotated about +z relative to objcam's convention (0 when
        objcam.envmap's Mitsuba conversion is right): sample the emitter with one lit texel and see where the
        directions land. Nonzero values are compensated (and reported by the transport stage)."""
        import drjit as dr

        from objcam.envmap import EnvGrid

        mi = use_mitsuba()
        h = self.env_height
        r0, c0 = h // 4, 1
        self._set_env(self.onehot([r0 * 2 * h + c0]))
        em = self.geo.mi_scene.emitters()[0]
        n = 256
        rng = np.random.default_rng(0)
        u = rng.random((2, n)).astype(np.float32)
        it = dr.zeros(mi.Interaction3f, n)
        ds, _ = em.sample_direction(it, mi.Point2f(u[0], u[1]))
        d = np.asarray(ds.d, dtype=np.float64).T
        r, c = EnvGrid(h).texel_of(d / np.linalg.norm(d, axis=1, keepdims=True))
        rr = np.bincount(r, minlength=h).argmax()
        cc = np.bincount(c, minlength=2 * h).argmax()
        if rr != r0:
            raise RuntimeError(f"Mitsuba envmap rows do not match objcam's convention (texel row {r0} lands in "
                               f"row {rr}); see objcam/envmap.py")
        return int((cc - c0) % (2 * h))

    def _set_env(self, env: np.ndarray) -> None:
        import drjit as dr

        from objcam.render import mitsuba_box_bitmap

        mi = use_mitsuba()
        if self._params is None:
            self._params = mi.traverse(self.geo.mi_scene)
        key = "emitter.data"
        cur = self._params[key]
        if self.column_offset:
            env = np.roll(env, -self.column_offset, axis=1)
        bm = to_mitsuba_bitmap(mitsuba_box_bitmap(env.astype(np.float32), self.upsample))
        data = np.concatenate([bm[:, -1:], bm, bm[:, :1]], axis=1)  # Mitsuba pads one wrapped column per side
        if tuple(cur.shape) != data.shape:
            raise RuntimeError(f"envmap emitter data has shape {tuple(cur.shape)}, expected {data.shape}: "
                               "build the SceneGeometry with the same env_height and upsample")
        self._params[key] = mi.TensorXf(padded(data, np.float32))  # objcam.dr_memory
        self._params.update()
        dr.eval()

    def onehot(self, texels: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        h = self.env_height
        env = np.zeros((h, 2 * h, 3), np.float32)
        texels = np.atleast_1d(np.asarray(texels, dtype=np.int64))
        r, c = np.divmod(texels, 2 * h)
        env[r, c] = 1.0 if weights is None else np.asarray(weights, np.float32)[:, None]
        return env

    def render(self, env: np.ndarray, spp: int, max_depth: int, seed: int, scale: int = 1,
               detail: np.ndarray | None = None, detail_spp: int | None = None) -> np.ndarray:
        """(M, 3) radiance of the kept pooled pixels under ``env`` (H, 2H, 3).

        scale > 1 renders a coarser image (pooled pixels grouped by ``scale``) and interpolates it bilinearly at
        the kept pixels' centres: for smooth signals (indirect light) only. ``detail`` (M,) bool marks pixels
        rendered at their own footprint instead (``detail_spp`` samples, default ``spp``): where the signal is
        not smooth, e.g. on and around the object, whose indirect light differs from the plane's beside it.
        """
        from objcam.render import render_image, render_rays

        self._set_env(env)
        self.renders += 1
        cam = self.pooled

        def exact(pix: np.ndarray, n: int) -> np.ndarray:
            row, col = np.divmod(pix, cam.width)
            return render_rays(self.geo.mi_scene, col.astype(np.float32), row.astype(np.float32), cam, n,
                               max_depth, seed)

        if scale <= 1:
            return exact(self.pixel_index, spp)
        coarse = scaled_camera(cam, scale)
        img = render_image(self.geo.mi_scene, coarse, spp, max_depth, seed)
        out = upsample_at(img, self.pixel_index, cam.width, scale)
        if detail is not None and detail.any():
            out[detail] = exact(self.pixel_index[detail], int(detail_spp or spp))
        return out


def upsample_at(img: np.ndarray, pixel_index: np.ndarray, width: int, scale: int) -> np.ndarray:
    """Bilinear samples (M, C) of a coarse image (h, w, C) (pixel U covers fine pixels scale U .. scale U +
    scale - 1) at the centres of the fine pixels ``pixel_index`` (flat, fine width ``width``); edges clamp."""
    from scipy.ndimage import map_coordinates

    row, col = np.divmod(np.asarray(pixel_index, dtype=np.int64), width)
    y = (row + 0.5) / scale - 0.5
    x = (col + 0.5) / scale - 0.5
    return np.stack([map_coordinates(img[..., c], [y, x], order=1, mode="nearest") for c in range(img.shape[2])],
                    axis=1).astype(np.float32)
