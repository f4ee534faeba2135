"""Stage ``solve``: recover each target's environment map from its transport matrix A (known albedo).

min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2, x >= 0, per colour channel, solved exactly in the Gram form.
One Gram matrix serves every channel (grey A) and every target that shares A and its valid pixels.

Writes per target ``<target>/``: envmap.exr (full lat-long, 0 where unsolved), envmap_mask.png (255 = solved
texel), prediction.exr, residual.exr (target - prediction, 0 at unused pixels), target.exr (the pooled target
that was fitted), tonemapped PNGs of each, and solve.json.
"""

from __future__ import annotations

import json
import time
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.envmap import EnvGrid
from objcam.errors import StageError
from objcam.image_io import atomic_write_text, write_exr, write_png, write_tonemapped_png
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.artifacts import SceneArtifact
from objcam.solvers.regularization import DEFAULT_LR_REL
from objcam.threads import single_blas_thread

NAME = "solve"
DEPS = ("scene", "transport")
VERSION = "1"
CODE_DEPS = ("objcam.solvers", "objcam.transport")


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    method: Literal["exact", "paper"] = Field("exact", description="exact bound-constrained minimiser, or the "
                                              "method's damped Newton steps with clipping (baseline)")
    # 0.1 measured best (tonemapped RMSE and SSIM) on the bundled demo and bench targets, whose path-tracing
    # noise is ~1-2% per pixel; noise-free synthetic data prefer ~1e-4 (bench/results.md)
    ls: float = Field(0.1, ge=0, description="smoothness weight, relative to mean(diag(A^T A))")
    lr: float = Field(DEFAULT_LR_REL, ge=0, description="L2 (ridge) weight, relative to mean(diag(A^T A))")


def _pixels(transport, image: np.ndarray, valid: np.ndarray):
    """The pooled target at A's rows: y (M, 3) and usable (M,) bool."""
    from objcam.transport import pool_target

    img, ok = pool_target(image, valid, transport.downsample)
    y = img.reshape(-1, 3)[transport.pixel_index].astype(np.float64)
    use = ok.reshape(-1)[transport.pixel_index]
    return img, ok, y, use


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam import solvers
    from objcam.transport import load_transport

    scene = SceneArtifact.load(inputs.upstream["scene"])
    out = inputs.out
    per_target: dict[str, dict] = {}
    gram_cache: dict[tuple, np.ndarray] = {}
    t_all = time.perf_counter()
    for target in scene.targets:
        tr = load_transport(inputs.upstream["transport"], target.name)
        image = target.load_image(scene.folder)
        valid = target.load_valid(scene.folder)
        pooled, pooled_ok, y, use = _pixels(tr, image, valid)
        if not use.any():
            raise StageError("no usable pixel sees the scene", scene.folder / target.image,
                             "check the camera pose and the valid mask")
        grid = EnvGrid(tr.env_height)
        C = tr.A.shape[0]
        t0 = time.perf_counter()
        X, kkt, obj, iters = np.zeros((tr.A.shape[2], 3)), np.zeros(3), np.zeros(3), 0
        grams = None
        with single_blas_thread():
            for c in range(C):
                # one Gram matrix per (A, channel, usable pixels): shared by every channel of a grey A and by
                # every target that shares the camera and the valid mask
                key = (str(tr.folder), c, hash(use.tobytes()))
                Ac = tr.A[c][use]
                if key not in gram_cache:
                    # the transport stage stored A^T A over all kept pixels; remove the few excluded rows
                    grams = tr.gram() if grams is None else grams
                    G = grams[c]
                    if not use.all():
                        G = G - solvers.gram(tr.A[c][~use])
                    ls_abs, lr_abs = solvers.absolute_weights(G, params.ls, params.lr)
                    D = solvers.difference_operator(grid, tr.texel_index)
                    gram_cache[key] = solvers.regularized_gram(G, D, ls_abs, lr_abs)
                Q = gram_cache[key]
                chans = [0, 1, 2] if C == 1 else [c]
                Yc = y[use][:, chans]
                B = solvers.rhs(Ac, Yc)
                res = (solvers.solve_exact if params.method == "exact" else solvers.solve_paper)(Q, B)
                X[:, chans] = res.x
                kkt[chans], iters = res.kkt_residual, max(iters, res.iterations)
                obj[chans] = solvers.objective(Q, B, res.x, np.einsum("ij,ij->j", Yc, Yc))
        solve_s = time.perf_counter() - t0

        env = tr.envmap_from_x(X)
        mask = np.zeros(grid.n_texels, bool)
        mask[tr.texel_index] = True
        mask = mask.reshape(grid.shape)
        pred = tr.predict(X)
        resid = np.where(pooled_ok[..., None], pooled - pred, 0.0)

        d = out / target.name
        write_exr(d / "envmap.exr", env)
        write_png(d / "envmap_mask.png", mask.astype(float))
        write_exr(d / "prediction.exr", pred)
        write_exr(d / "residual.exr", resid)
        write_exr(d / "target.exr", pooled)
        write_tonemapped_png(d / "envmap.png", env)
        ref = write_tonemapped_png(d / "target.png", pooled)
        write_tonemapped_png(d / "prediction.png", pred, exposure_ref=ref)
        write_tonemapped_png(d / "residual.png", np.abs(resid), exposure_ref=ref)

        fit = pred.reshape(-1, 3)[tr.pixel_index][use]
        rel_res = float(np.linalg.norm(fit - y[use]) / max(np.linalg.norm(y[use]), 1e-30))
        info = {
            "method": params.method, "texels": int(len(tr.texel_index)), "pixels_used": int(use.sum()),
            "pixels_excluded": int((~use).sum()), "channels_in_A": int(C), "solve_seconds": round(solve_s, 4),
            "iterations": int(iters), "kkt_residual_max": float(kkt.max()), "objective": obj.tolist(),
            "relative_image_residual": rel_res, "ls_relative": params.ls, "lr_relative": params.lr,
        }
        atomic_write_text(d / "solve.json", json.dumps(info, indent=2))
        per_target[target.name] = info
    total = time.perf_counter() - t_all
    worst_kkt = max(v["kkt_residual_max"] for v in per_target.values())
    summary = (f"{len(per_target)} target(s), {params.method}, {total:.2f} s; KKT residual <= {worst_kkt:.1e}; "
               + ", ".join(f"{k}: image residual {v['relative_image_residual']:.3f}" for k, v in per_target.items()))
    return StageOutputs(metrics={"targets": per_target, "seconds": round(total, 4)}, summary=summary)
