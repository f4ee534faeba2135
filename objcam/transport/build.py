"""Build the transport matrix of one camera into a zarr group (see objcam.transport.storage)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from objcam.camera import Camera
from objcam.envmap import EnvGrid
from objcam.progress import bar
from objcam.transport.geometry import SampleParts, SceneGeometry, primary_samples
from objcam.transport.pixels import pool_target, pooled_shape
from objcam.transport.storage import ColumnWriter


@dataclass
class BuildSettings:
    model: str = "auto"  # auto | direct | path
    env_height: int = 32  # A's grid
    output_height: int | None = None  # the envmap asked for (None: env_height; see objcam.solvers.refine)
    samples: int = 4
    subpixel_samples: int = 32
    object_samples: int = 16
    object_subpixel_samples: int = 256
    refine: bool = True
    texel_kernel: float = 1.0  # shadow rays into the texel's central fraction per side (objcam.transport.kernel)
    auto_choice: str | None = None  # model=auto: take this choice ("direct" or "direct+indirect"), not measure it
    downsample: int = 1
    seed: int = 0
    use_valid: bool = True
    batch_rays: int = 1 << 24
    chunk_columns: int = 128
    path_spp: int = 64
    path_max_depth: int = 8
    path_upsample: int = 8
    auto_columns: int = 16
    auto_spp: int = 32
    auto_max_depth: int = 6
    auto_noise: float | None = None
    correction_scale: int = 4
    correction_spp: int = 32
    correction_texel_block: int = 4
    correction_detail_px: int = 3
    correction_detail_spp: int = 128
    indirect: str = "gather"  # auto's indirect light: gather (objcam.transport.gather) | path (IndirectCorrection)
    gather_rays: int = 256
    gather_node_rays: int = 64
    pair_budget: int = 1 << 22  # (pixel, texel) pairs classified per block


class _CpuLaps:
    """CPU seconds of this process (time.process_time: every thread) between named laps."""

    def __init__(self):
        self.t = time.process_time()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.process_time()
        self.laps[name] = self.laps.get(name, 0.0) + now - self.t
        self.t = now

    def metrics(self) -> dict:
        return {f"cpu_seconds_{k}": round(v, 3) for k, v in self.laps.items()} | \
            {"cpu_seconds": round(sum(self.laps.values()), 3)}


def candidate_pixels(camera: Camera, f: int, valids: list[np.ndarray] | None) -> np.ndarray:
    """Flat pooled-pixel indices worth computing: those valid (whole block) in at least one target."""
    hp, wp = pooled_shape(camera.height, camera.width, f)
    if not valids:
        return np.arange(hp * wp, dtype=np.int64)
    ok = np.zeros((hp, wp), bool)
    for v in valids:
        ok |= pool_target(np.zeros(v.shape + (3,), np.float32), v, f)[1]
    return np.nonzero(ok.ravel())[0].astype(np.int64)


def build_camera(geo: SceneGeometry, camera: Camera, folder: Path, s: BuildSettings, *,
                 valids: list[np.ndarray] | None = None, targets: list[str] | None = None,
                 target_noise: tuple[float, str] | None = None, hold: dict | None = None) -> dict:
    """Compute A for ``camera`` into the zarr group ``folder``; returns the metrics.

    valids: the targets' (H, W) valid masks (pixels invalid in all of them are not computed).
    target_noise: (relative noise, where it came from) for model=auto; default 1% ("assumed").
    hold: a dict that receives the direct-light model as "direct" (objcam.transport.kernel recomputes columns).
    """
    from objcam.transport.engine import current

    engine = current()  # in this process, or shards on a Dask cluster (objcam.transport.shards)
    t0 = time.perf_counter()
    cpu = _CpuLaps()  # this process's CPU per phase (Dr.Jit's threads included), beside the wall times
    f, k = int(s.downsample), int(s.samples)
    hp, wp = pooled_shape(camera.height, camera.width, f)
    grid = EnvGrid(s.env_height)
    n_total = grid.n_texels
    channels = 1 if geo.desc.albedo_is_grey() else 3
    cand = candidate_pixels(camera, f, valids if s.use_valid else None)
    n_sub = k * -(-max(int(s.subpixel_samples), k) // k)  # a multiple of K
    samples = primary_samples(geo, camera, f, n_sub, cand, wp, s.seed)
    keep = samples.hit.any(axis=1)
    samples = samples.subset(keep)
    m = int(keep.sum())
    if m == 0:
        from objcam.errors import StageError

        names = ", ".join(targets or []) or "a target"
        raise StageError(f"no valid pixel of {names} sees the object or the support",
                         fix="check the camera pose (world_from_camera is camera-to-world, OpenCV axes) and the "
                             "valid mask")
    metrics: dict = {"pixels_kept": m, "pixels_total": hp * wp, "pixels_candidate": int(cand.size),
                     "texels_total": n_total, "channels": channels, "samples": k, "subpixel_samples": n_sub,
                     "downsample": f}
    writer = ColumnWriter(folder, channels, m, n_total, s.chunk_columns)
    model = s.model
    dm = pr = None
    parts = SampleParts.single(samples)
    if model in ("direct", "auto"):
        from objcam.transport.direct import DirectModel, SplitDirect

        # pixels that see the object: their faceted normals and its silhouette vary inside the pixel, so they get
        # more sub-pixel samples and shadow rays (measured on the bench bunny: object-pixel error 0.87% at 32 x 4,
        # 0.32% at 256 x 16, for ~1 s more)
        obj_rows = samples.on_object.any(axis=1)
        k_o = max(int(s.object_samples), 1)
        n_o = k_o * -(-max(int(s.object_subpixel_samples), k_o) // k_o)
        rays = [k]
        if obj_rows.any() and (n_o > n_sub or k_o > k):
            rows_o, rows_s = np.flatnonzero(obj_rows), np.flatnonzero(~obj_rows)
            s_obj = primary_samples(geo, camera, f, n_o, samples.pixel_index[rows_o], wp, s.seed + 1)
            parts = SampleParts(samples.pixel_index, [(rows_s, samples.subset(~obj_rows)), (rows_o, s_obj)])
            rays = [k, k_o]
            metrics.update({"object_pixels": int(rows_o.size), "object_samples": k_o,
                            "object_subpixel_samples": n_o})
        dm = SplitDirect([(rows, DirectModel(geo, ps, s.env_height, channels, rays=kk, seed=s.seed,
                                             batch_rays=s.batch_rays, refine=s.refine, image_shape=(hp, wp),
                                             kernel=s.texel_kernel))
                          for (rows, ps), kk in zip(parts.parts, rays) if rows.size], m)
        if hold is not None:
            hold["direct"] = dm
        rows_per = max(1, s.pair_budget // max(1, m * grid.width))
        blocks = [np.arange(r0 * grid.width, min(grid.height, r0 + rows_per) * grid.width)
                  for r0 in range(0, grid.height, rows_per)]
        cpu.lap("setup")
        with bar(total=n_total, desc=f"transport: direct K={k}", unit="texel") as pb:
            for tex, cols in engine.direct_columns(dm, blocks, folder):  # in order, wherever they were computed
                nz = np.any(cols != 0, axis=(0, 1))
                writer.append(tex[nz], cols[:, :, nz])
                pb.update(tex.size)
        cpu.lap("direct")
        st = dm.stats
        metrics.update({"rays_traced": st.rays_traced, "rays_culled": st.rays_culled, "rays_total": st.rays_total,
                        "pairs_zero": st.pairs_zero, "pairs_analytic": st.pairs_analytic,
                        "pairs_traced": st.pairs_traced, "pairs_refined": st.pairs_refined,
                        "pairs_settled": st.pairs_settled})
    elif model == "path":
        from objcam.transport.path import PathRenderer

        pr = PathRenderer(geo, camera, f, samples.pixel_index, s.env_height)
        with bar(total=n_total, desc=f"transport: path spp={s.path_spp}", unit="texel") as pb:
            for j in range(n_total):
                y = pr.render(pr.onehot([j]), s.path_spp, s.path_max_depth, seed=s.seed * 1_000_003 + j)
                col = y.mean(axis=1)[None] if channels == 1 else y.T
                if np.any(col != 0):
                    writer.append(np.array([j]), col[:, :, None])
                pb.update(1)
        metrics.update({"renders": pr.renders, "path_spp": s.path_spp, "path_max_depth": s.path_max_depth})
        if pr.column_offset:
            metrics["mitsuba_envmap_column_offset"] = pr.column_offset
    elif model not in ("direct", "auto", "path"):
        raise ValueError(f"unknown transport model {model!r}")
    texel_index = writer.texel_index
    metrics["seconds_direct" if model != "path" else "seconds_path"] = round(time.perf_counter() - t0, 3)

    chosen = "direct" if model == "auto" else model
    if model == "auto" and texel_index.size:
        from objcam.transport.auto import (AUTO_STOP_MARGIN, IndirectCorrection, choose_columns, detail_pixels,
                                           measure)
        from objcam.transport.path import PathRenderer

        noise, source = target_noise if target_noise is not None else (0.01, "assumed")
        if s.auto_noise is not None:  # per photo pixel, as noise_sigma
            noise, source = float(s.auto_noise) / max(int(f), 1), "param"
        pr = PathRenderer(geo, camera, f, samples.pixel_index, s.env_height)
        # the columns in the order farthest-point sampling picked them (every prefix spread over the sphere), each
        # seeded by its rank among them, so a full measurement is the one the sorted columns gave; the direct
        # light of a column is computed only when it is measured (measure stops once the choice is clear)
        if s.auto_choice is None:
            pos = choose_columns(texel_index, writer.column_norms, s.auto_columns, s.env_height,
                                 spread_order=True)
            unknown = parts.unknown_albedo()
            rep = measure(pr, dm.columns, texel_index[pos], s.auto_spp, s.auto_max_depth, s.seed,
                          s.correction_scale, noise, source, pins=~unknown if unknown.any() else None,
                          seeds=np.argsort(np.argsort(pos)), stop_margin=AUTO_STOP_MARGIN)
            metrics.update(rep.metrics())
            chosen = rep.choice
        else:  # decided on another A of the same scene (objcam.transport.kernel's second kernel)
            chosen = s.auto_choice
            metrics["auto_choice_given"] = chosen
        cpu.lap("auto_measure")
        if pr.column_offset:
            metrics["mitsuba_envmap_column_offset"] = pr.column_offset
        if chosen != "direct":
            t1 = time.perf_counter()
            writer.flush()
            if s.indirect == "gather":
                from objcam.transport.gather import GatherIndirect, GatherSettings

                gs = GatherSettings(rays=s.gather_rays, node_rays=s.gather_node_rays, max_depth=s.auto_max_depth,
                                    seed=s.seed)
                # the support's bounce albedo is a guess: keep what redoing its light needs (bounce.npz)
                guessed = bool(parts.unknown_albedo().any()) and geo.plane is not None
                gi = GatherIndirect(geo, parts, texel_index, s.env_height, channels, gs, batch_rays=s.batch_rays,
                                    keep_parts=guessed)
                cpu.lap("gather_setup")
                engine.add_indirect(folder, gi)
                cpu.lap("gather_columns")
                metrics.update(gi.metrics())
                if guessed:
                    from objcam.transport.storage import write_bounce

                    write_bounce(folder, gi.bounce_parts())
                    metrics["bounce_parts"] = True
            elif s.indirect == "path":
                detail = detail_pixels(parts.object_fraction(), samples.pixel_index, (hp, wp),
                                       s.correction_detail_px)
                corr = IndirectCorrection(pr, texel_index, s.env_height, s.correction_texel_block,
                                          s.correction_spp, s.auto_max_depth, s.seed, s.correction_scale, detail,
                                          s.correction_detail_spp)
                metrics["correction_detail_pixels"] = int(detail.sum())
                corr.compute_all()  # path-traced renders: in this process whatever the engine
                from objcam.transport.storage import add_to_columns

                add_to_columns(folder, lambda a, b: corr.columns(a, b, channels))
                metrics["correction_renders"] = corr.renders
            else:
                raise ValueError(f"unknown indirect model {s.indirect!r}")
            metrics["indirect"] = s.indirect
            metrics["correction_seconds"] = round(time.perf_counter() - t1, 3)

    dirs = grid.directions().reshape(-1, 3)[texel_index].astype(np.float32)
    omega = grid.solid_angles().ravel()[texel_index].astype(np.float32)
    arrays = {"pixel_index": samples.pixel_index.astype(np.int64), "texel_index": texel_index,
              "directions": dirs, "solid_angle": omega, "albedo": parts.albedo(),
              "unknown_albedo": parts.unknown_albedo(), "coverage": parts.coverage(),
              "object_fraction": parts.object_fraction()}
    metrics["texels_kept"] = int(texel_index.size)
    metrics["model"] = chosen
    metrics["seconds"] = round(time.perf_counter() - t0, 3)
    cpu.lap("finish")
    metrics.update(cpu.metrics())
    attrs = {"image_shape": [hp, wp], "downsample": f, "env_height": s.env_height,
             "output_height": s.output_height or s.env_height, "channels": channels,
             "model": chosen, "model_requested": model, "samples": k if model != "path" else None,
             "subpixel_samples": n_sub,
             "spp": s.path_spp if model == "path" else (s.auto_spp if model == "auto" else None),
             "max_depth": s.path_max_depth if model == "path" else (s.auto_max_depth if chosen == "direct+indirect"
                                                                    else 2),
             "camera": camera.model_dump(), "targets": targets or [], "metrics": metrics, "seed": s.seed}
    writer.finish(arrays, attrs)
    return metrics
