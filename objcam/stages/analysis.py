"""Stage ``analysis``: what the object-camera can see (the method's Section 5).

Per camera (one A): the leverage of every pixel h_ii = a_i (A^T A + lr I)^-1 a_i^T, the per-texel uncertainty
sqrt(diag((A^T A + lr I)^-1)) (smoothness prior left out, as in the method), the singular spectrum of A with its
effective rank, and gain images (rows of (A^T A + R)^-1 A^T, R = ls D^T D + lr I) for a few directions.
Per target: Cook's distance of every pixel for the solve's fit (luminance).

Writes ``<group>/`` leverage.exr/.png, uncertainty.exr/.png, spectrum.png, gains.png and ``<target>/``
cooks.exr/.png, plus analysis.json. A colour A (C = 3) is analysed on its channel-mean transport.
"""

from __future__ import annotations

import json

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from objcam.envmap import EnvGrid, read_latlong, write_latlong
from objcam.image_io import atomic_write_text, write_exr
from objcam.pipeline.stage import StageInputs, StageOutputs
from objcam.schemas.artifacts import SceneArtifact

NAME = "analysis"
DEPS = ("scene", "transport", "solve")
VERSION = "1"
CODE_DEPS = ("objcam.analysis",)


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lr: float = Field(1e-4, gt=0, description="ridge weight of the uncertainty and leverage, relative to "
                                               "mean(diag(A^T A))")
    gain_directions: int = Field(6, ge=0, le=24, description="gain images for this many directions: the brightest "
                                                             "recovered texel and texels spread over the sky")
    rank_tol: float = Field(1e-3, gt=0, lt=1, description="effective rank: singular values above tol x the largest")


def _solved_ls(solve_dir, name: str, solve_params: dict) -> float:
    """The relative smoothness weight the solve used for target ``name`` (its solve.json; ls may be chosen per
    target from its noise)."""
    try:
        return float(json.loads((solve_dir / name / "solve.json").read_text())["ls_relative"])
    except (FileNotFoundError, KeyError, TypeError, ValueError):
        return float(solve_params.get("ls") or 0.1)


def _gain_texels(grid: EnvGrid, texel_index: np.ndarray, brightest: int | None, k: int) -> list[int]:
    """Column indices: the brightest recovered texel, then texels spread in elevation and azimuth."""
    if k == 0:
        return []
    r, c = np.divmod(texel_index, grid.width)
    picks = [] if brightest is None else [int(brightest)]
    rows = np.linspace(r.min(), r.max(), max(2, (k + 1) // 2)).round().astype(int)
    for i, row in enumerate(rows):
        for col in (grid.width // 4 + i * grid.width // 7, 3 * grid.width // 4 + i * grid.width // 7):
            hit = np.flatnonzero((r == row) & (c == col % grid.width))
            if hit.size and int(hit[0]) not in picks:
                picks.append(int(hit[0]))
    return picks[:k]


def _direction_label(grid: EnvGrid, flat: int) -> str:
    r, c = divmod(int(flat), grid.width)
    theta, phi = grid.centres()
    return f"elev {90 - np.degrees(theta[r, c]):.0f}, az {np.degrees(phi[r, c]):.0f} deg"


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam import analysis as an
    from objcam.solvers import absolute_weights, gram
    from objcam.transport import load_transport, pool_target
    from objcam.transport.storage import read_index

    scene = SceneArtifact.load(inputs.upstream["scene"])
    solve_dir, out = inputs.upstream["solve"], inputs.out
    solve_params = json.loads((solve_dir / "stage.json").read_text())["params"]
    index = read_index(inputs.upstream["transport"])
    results: dict = {"groups": {}, "targets": {}}
    done_groups: dict[str, tuple] = {}
    for target in scene.targets:
        group = index["targets"][target.name]
        tr = load_transport(inputs.upstream["transport"], target.name)
        grid = EnvGrid(tr.env_height)
        A = tr.A[0] if tr.channels == 1 else tr.A.mean(axis=0)
        # the target's solved envmap at the kept texels, RGB (N, 3)
        # (on A's grid: a supersampled transport's solve writes it as envmap_fine.exr, objcam.solvers.refine)
        sdir = solve_dir / target.name
        env_file = next(p for p in (sdir / "envmap_fine.exr", sdir / "envmap.exr") if p.is_file())
        x_solved = read_latlong(env_file)[..., :3].reshape(-1, 3)[tr.texel_index]
        if group not in done_groups:
            G = tr.gram()[0] if tr.channels == 1 else gram(A)
            lr = absolute_weights(G, 0.0, params.lr)[1]
            gdir = out / group
            L = an.cholesky_factor(G, lr)
            h = an.leverage(A, lr, L=L)
            unc = an.texel_uncertainty(None, lr, L=L)
            sv = an.singular_spectrum(A, G=G)
            h_img = an.scatter_to_image(h, tr.pixel_index, tr.image_shape)
            u_map = an.to_grid(unc, grid, tr.texel_index)
            write_exr(gdir / "leverage.exr", np.nan_to_num(h_img))
            write_latlong(gdir / "uncertainty.exr", np.nan_to_num(u_map))
            an.plot_image_map(h_img, gdir / "leverage.png", title="leverage h_ii (pixels the solve leans on)",
                              units="h_ii", log=True)
            an.plot_envmap_map(u_map, gdir / "uncertainty.png", log=True,
                               title="per-texel uncertainty sqrt(diag((A^T A + lr I)^-1))",
                               units="radiance per unit pixel noise")
            an.plot_spectrum(sv, gdir / "spectrum.png", tol=params.rank_tol, lr=lr,
                             title=f"singular spectrum of A ({A.shape[0]:,} px x {A.shape[1]:,} texels)")
            brightest = int(np.argmax(x_solved.mean(axis=1))) if x_solved.size else None
            cols = _gain_texels(grid, tr.texel_index, brightest, params.gain_directions)
            if cols:
                ls_rel = _solved_ls(solve_dir, target.name, solve_params)
                ls_abs, _ = absolute_weights(G, ls_rel, 0.0)
                R = an.regularizer(grid, tr.texel_index, ls_abs, lr)
                rows = an.gain_images(A, R, cols, G=G)
                imgs = an.scatter_to_image(rows, tr.pixel_index, tr.image_shape)
                an.plot_image_grid(list(imgs), gdir / "gains.png", suptitle="gain images: rows of "
                                   "(A^T A + R)^-1 A^T (how each pixel moves one texel)",
                                   titles=[_direction_label(grid, tr.texel_index[c]) for c in cols],
                                   units="radiance per pixel value")
            upper = tr.directions[:, 2] > 0
            g = {
                "pixels": int(A.shape[0]), "texels": int(A.shape[1]),
                "effective_rank": int(an.effective_rank(sv, params.rank_tol)),
                "entropy_effective_rank": float(an.entropy_effective_rank(sv)),
                "ridge_dof": float(an.ridge_dof(sv, lr)),
                "condition_number": float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
                "leverage_sum": float(h.sum()), "leverage_max": float(h.max()),
                "uncertainty_mean_upper": float(unc[upper].mean()) if upper.any() else None,
                "uncertainty_worst_upper": float(unc[upper].max()) if upper.any() else None,
                "lr_absolute": float(lr),
            }
            results["groups"][group] = g
            done_groups[group] = (L, h, lr)
        L, h, lr = done_groups[group]
        image, _ = pool_target(target.load_image(scene.folder), target.load_valid(scene.folder), tr.downsample)
        y = tr.pixels_of(image).mean(axis=1).astype(np.float64)
        d = an.cooks_distance(A, y, x_solved.mean(axis=1).astype(np.float64), lr, h=h, L=L)
        d_img = an.scatter_to_image(d, tr.pixel_index, tr.image_shape)
        write_exr(out / target.name / "cooks.exr", np.nan_to_num(d_img))
        an.plot_image_map(d_img, out / target.name / "cooks.png", log=True,
                          title=f"{target.name}: Cook's distance (influence of each pixel on the fit)",
                          units="D_i")
        results["targets"][target.name] = {"cooks_max": float(np.nanmax(d)),
                                           "cooks_over_4_over_M": int((d > 4.0 / d.size).sum())}
    clean = json.loads(json.dumps(results, default=float).replace("Infinity", "null").replace("NaN", "null"))
    atomic_write_text(out / "analysis.json", json.dumps(clean, indent=2))
    first = next(iter(results["groups"].values()))
    summary = (f"effective rank {first['effective_rank']} of {first['texels']} texels; uncertainty mean "
               f"{first['uncertainty_mean_upper']:.3g}, worst {first['uncertainty_worst_upper']:.3g} (upper sky)")
    return StageOutputs(metrics=clean, summary=summary)
