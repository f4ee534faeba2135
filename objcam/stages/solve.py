"""Stage ``solve``: recover each target's environment map from its transport matrix A (and, where the capture
leaves it unknown, the albedo).

Known albedo (no kept pixel has ``unknown_albedo``): min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2, x >= 0,
per colour channel, solved exactly in the Gram form. One Gram matrix serves every channel (grey A) and every
target that shares A and its valid pixels. The default edge prior (objcam.solvers.edges) with a grey A takes the
envmap's luminance from that solve and its chroma from a second one at ``chroma_ls_factor`` x ls
(objcam.solvers.chroma), run on a second thread.

Unknown albedo: the joint solve (objcam.solvers.joint) of ``y_l = diag(rho_p) A'_p x_l`` for the albedo rho_p of
every camera p and the envmap x_l of every illumination l, grouped as objcam.solvers.assemble says (targets of one
camera share rho; targets with the same ``illumination`` name in capture.toml share x). The smoothness weight
ls may be chosen per problem by ``auto_reg`` (objcam.solvers.jointauto); the default is a measured fixed weight
(bench/results.md, "Joint solve ablation"). The envmap and the
albedo are then known only up to one scale per colour channel (c rho, x / c fit equally): solve.json says so and
evaluate compares after the best-fit scale. A final step follows (``final_envmap=known``): rounds of the albedo's
exact step with a total-variation prior (objcam.solvers.albedo_tv: a free per-pixel albedo absorbs what the envmap
estimate gets wrong as faint shadows, which a print's piecewise-constant albedo does not have) and every envmap at
that albedo, held fixed, by the known-albedo solver (tone-weighted edges, ls from the noise).

Both solve for the envmap on a merged basis (objcam.solvers.basis, ``texel_group``): near the poles a row's
texels are joined into groups of about one equator texel's solid angle, the objective unchanged over envmaps
constant on each group; the envmap is written back on the full lat-long grid.

A supersampled transport (``transport.supersample`` 2: A on a 2x finer grid than the envmap asked for; known
albedo only, method exact or paper) is solved on the adaptive basis of objcam.solvers.refine: output texels, except the
``refine_fraction`` with the most contrast in a pilot solve, which keep their fine texels. envmap.exr is the
result area-averaged to the output grid; envmap_fine.exr and envmap_fine_mask.png hold it on A's grid.

``method=adam``: the gradient-descent baseline through Mitsuba's differentiable renderer (objcam.solvers.adam),
on the texels.

Writes per target ``<target>/``: envmap.exr (full lat-long, 0 where unsolved), envmap_mask.png (255 = solved
texel), prediction.exr, residual.exr (target - prediction, 0 at unused pixels), target.exr (the pooled target
that was fitted), tonemapped PNGs of each, and solve.json; with unknown albedo also albedo.exr (pooled image
size, 0 where not estimated), albedo.png and albedo_mask.png (255 where the albedo was unknown and estimated).
"""

from __future__ import annotations

import dataclasses
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
from objcam.solvers.basis import merge_gram, texel_basis, unknowns
from objcam.solvers.refine import average_to, coarse_of, contrast, refined_basis, split_by_contrast
from objcam.solvers.regularization import DEFAULT_LR_REL
from objcam.threads import parallel_map, single_blas_thread

NAME = "solve"
DEPS = ("scene", "transport")
VERSION = "5"
CODE_DEPS = ("objcam.solvers", "objcam.transport")

#: Envmap basis (objcam.solvers.basis), the largest group per row in equator-texel solid angles. Measured on the
#: bench (bench/results.md, session 9): a known albedo resolves the polar texels' texture (forest SSIM 0.777 with
#: one unknown per texel, 0.775 at 1, 0.765 at sqrt 2; courtyard 0.787 / 0.785 / 0.786), so it merges only what
#: spans less than one equator texel; with unknown albedo the albedo, not the basis, limits the envmap (dots
#: scene SSIM 0.607 / 0.609 / 0.609) and sqrt 2 solves 1.4x faster than the texels.
TEXEL_GROUP_KNOWN = 1.0
TEXEL_GROUP_JOINT = float(np.sqrt(2.0))
#: Unknown-albedo smoothness when ls is not given: measured best on the bundled path-traced targets, whose
#: model error (indirect light, ~1-2% noise) GCV cannot see (bench/results.md).
KNOWN_LS_REL = 0.1
#: Known albedo, ls not given, prior=smooth (and method=paper): ls = factor x sigma^2 (sigma: relative pixel
#: noise), clipped to LS_RANGE. The joint (unknown-albedo) solve uses the same rule: measured near the best envmap
#: SSIM on the 3-illumination bench scene (bench/results.md).
LS_NOISE_FACTOR = 300.0
#: Known albedo, prior=edges (the default), ls not given: ls = factor x sigma. The Huber prior is scaled by the RMS
#: edge of the first (quadratic) solve, which grows with the noise, so the weight that balances the data grows like
#: sigma, not sigma^2. Measured with the tone weighting (bench/results.md): best ls ~1-2 sigma both on the bench's
#: 0.2-0.4% noise targets and on the 2.3% noise of `make demo` (SSIM 0.59 at 1.5 sigma against 0.48 at 600 sigma^2).
EDGE_LS_PER_SIGMA = 1.5
#: Known albedo, prior=edges: tone exponent, its floor and the Huber threshold. Measured on the bench's four HDRIs
#: (bench/results.md, objcam.solvers.edges): with ls 1.5 sigma against no tone weighting, eps 0.005 and
#: 300 sigma^2, SSIM courtyard 0.70 -> 0.79, sunrise 0.65 -> 0.74, forest 0.79 -> 0.78, city 0.86 -> 0.83, and
#: relative RMSE better on three of the four (city 1.50 -> 1.04, sunrise 4.9 -> 3.7).
EDGE_TONE = 0.3
EDGE_TONE_FLOOR = 0.05
EDGE_EPS_KNOWN = 0.001
#: Known albedo, prior=edges, grey A: the chroma's smoothness relative to the luminance's (objcam.solvers.chroma).
#: Measured on the bench (bench/results.md, session 11) at ls 1.5 sigma, SSIM forest / courtyard / city / sunrise:
#: one solve 0.775 / 0.785 / 0.828 / 0.736; chroma at 4x 0.774 / 0.841 / 0.831 / 0.732, 10x 0.772 / 0.856 / 0.831 /
#: 0.723, 20x 0.771 / 0.854 / 0.831 / 0.729.
CHROMA_LS_FACTOR = 10.0
#: Known albedo, prior=edges, supersampled A (transport.supersample 2, objcam.solvers.refine): ls = factor x sigma
#: on the fine grid (mean diag(A^T A) there is ~1/16 of the output grid's, and each output edge is two fine
#: edges: the output grid's 1.5 sigma is ~12 here). Measured on the bench's four HDRIs (bench/results.md, session
#: 12), SSIM forest / courtyard at 7 / 10 / 14 sigma: 0.808 / 0.797, 0.804 / 0.823, 0.794 / 0.839.
EDGE_LS_PER_SIGMA_SUPERSAMPLED = 10.0
#: Supersampled A: the fraction of output texels (those of most contrast in a pilot solve) solved on the fine
#: grid. Measured (same bench, 10 sigma): 0 (every output texel one unknown) forest 0.791 / courtyard 0.821,
#: 0.1 0.804 / 0.823, 0.2 0.807 / 0.820, all fine texels 0.808 / 0.825 at 5-10x the time.
REFINE_FRACTION = 0.2
#: Joint solve: the Huber threshold (its edge prior is untoned; 0.005 measured on the bench scenes).
EDGE_EPS_JOINT = 0.005
LS_RANGE = (3e-4, 0.3)
#: Joint solve with auto_reg: the smoothness (relative to A', albedo 1) of the provisional solve whose albedo the
#: criterion is evaluated at. On the 3-illumination 'dots' scene (bench/results.md) GCV, the discrepancy principle
#: and the L-curve all chose the floor of their grid (~1e-8: envmap SSIM 0.10 against 0.31-0.34 at fixed weights),
#: because the residual is dominated by model error (interreflections rendered at albedo 1, shadow discretisation)
#: that none of them models; hence auto_reg is off by default.
JOINT_LS0_REL = 1e-2
#: Joint solve: stop when a sweep lowers the objective by less than this fraction. On the 3-illumination bench
#: scene (split targets, edge prior) sweeps 8-9 at 1e-4 changed envmap SSIM by 0.0003 and albedo RMSE by 0.0001
#: against 1e-3 (7 sweeps), for 19% more time (bench/results.md).
JOINT_TOL = 1e-3
#: ... and when the final step (final_envmap=known) follows: the joint solve then only provides the albedo that the
#: TV step starts from. Measured on the dots bench scene: envmap SSIM 0.6669 at 1e-2 (4 sweeps) against 0.6666
#: at 1e-3 (7 sweeps), the same albedo error (bench/results.md).
JOINT_TOL_FINAL = 1e-2
#: Joint solve followed by a bounce refit: the first solve's stopping tolerance (relative decrease per sweep).
BOUNCE_FIRST_TOL = 3e-2
#: Joint solve, prior=edges: majorise-minimise x-steps per sweep (each reuses the sweep's Gram matrices). One
#: step per sweep (the weights are refreshed at every sweep anyway) measured on the dots bench scene: solve 17.5 ->
#: 15.9 s, envmap SSIM 0.602 -> 0.605, relative RMSE 0.659 -> 0.657, the same albedo (bench/results.md).
JOINT_EDGE_STEPS = 1
#: Joint solve followed by a bounce refit: the first solve fits one pixel in ``stride^2`` (a regular grid over the
#: image; every pixel of known albedo kept), then every pixel's albedo is its least-squares value at those
#: envmaps. The refit only needs the support's albedo averaged over its cells, and the second solve redoes every
#: pixel. Measured on the dots bench scene (stride 1 / 2 / 3 / 4): first solve 6.0 / 3.1 / 2.4 / 2.3 s, envmap
#: SSIM after the second solve 0.605 / 0.608 / 0.608 / 0.606. 2 keeps the subsample well over-determined: per
#: channel L M / 4 equations against M / 4 + L N unknowns, 1.7x there (stride 3: 1.07x).
BOUNCE_FIRST_STRIDE = 2
#: Joint solve: lp when not given. With one illumination per camera the albedo of each pixel can absorb the whole
#: image, so the albedo prior is what separates them; with two or more the data separate them and a smoothness
#: prior only blurs the albedo's edges (bench/results.md, joint ablation).
LP_ONE_ILLUMINATION = 1e-2

#: Unknown albedo, final step (_final_step): the TV albedo prior's contrast and the rounds of (albedo step, envmap
#: step). Measured on the dots bench scene (bench/results.md; joint solve to 1e-3, TV without the regions' refit):
#: envmap SSIM 0.638 without the TV step; contrast 0.004 / 0.006 / 0.008 / 0.012 at two rounds 0.670 / 0.674 /
#: 0.672 / 0.655 (albedo relative RMSE 0.0029 / 0.0034 / 0.0039 / 0.0052, the joint solve's 0.0031); rounds 1 / 2 /
#: 4 at 0.008: 0.668 / 0.672 / 0.673. With the joint solve to JOINT_TOL_FINAL and FINAL_EARLY_STEPS: one round
#: 0.667, two 0.675 (~1.2 s more); with the regions' least-squares refit (objcam.solvers.albedo_tv) 0.710, albedo
#: 0.0021.
ALBEDO_TV = 0.006
FINAL_ROUNDS = 2
#: Reweighting steps of the edge solve in the final step's rounds before the last (their envmaps only feed the next
#: albedo step). Measured on the dots bench scene, two rounds: 6 / 2 / 1 steps, SSIM 0.6743 / 0.6750 / 0.6731, the
#: final step 3.3 / 2.7 / 2.6 s.
FINAL_EARLY_STEPS = 2

SCALE_NOTE = ("unknown albedo: the envmap and the albedo are known only up to one scale per colour channel "
              "(c * albedo and envmap / c fit the photos equally); the regularisers pick c, and evaluate "
              "compares after the best-fit scale")


SCALE_PINNED_NOTE = ("unknown albedo, with pixels of known albedo held at it: they fix the scale that c * albedo "
                     "and envmap / c would otherwise leave free, so the envmap and the albedo are absolute")


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")
    method: Literal["exact", "paper", "adam"] = Field(
        "exact", description="exact bound-constrained minimiser (joint: exact alternation), the method's damped "
        "Newton steps with clipping (baseline), or Adam through Mitsuba's differentiable renderer (baseline)")
    ls: float | None = Field(None, ge=0, description="smoothness weight, relative to mean(diag(A^T A)) (unknown "
                             "albedo: A = diag(rho0) A' at the initial albedo, known values and 0.5); None: from "
                             "the target's noise, ls_noise_factor x sigma^2 (unknown albedo: the median over the "
                             "joint problem's targets); replaced by the auto_reg choice unless it is off")
    prior: Literal["edges", "smooth"] = Field("edges", description="edge-preserving (Huber) smoothness, solved "
                                              "exactly by reweighting (unknown albedo: inside the joint "
                                              "alternation), or the plain quadratic "
                                              "smoothness (one exact solve; fastest)")
    edge_steps: int = Field(6, ge=1, le=50, description="prior=edges: most reweighting steps (6: within 0.01 of "
                            "the SSIM of 25 on the bench's 4 HDRIs, 0.3-0.8 s for 1,088 texels)")
    edge_eps: float | None = Field(None, gt=0, description="prior=edges: Huber threshold relative to the RMS edge "
                                   f"(small: close to total variation); None: {EDGE_EPS_KNOWN} for a known albedo, "
                                   f"{EDGE_EPS_JOINT} for the joint solve (bench/results.md)")
    edge_tone: float = Field(EDGE_TONE, ge=0, le=1, description="prior=edges, known albedo: weight each edge by "
                             "(mean / (local radiance + floor x mean))^edge_tone, so structure counts in tonemapped "
                             "rather than linear units (objcam.solvers.edges); 0: plain Huber")
    edge_tone_floor: float = Field(EDGE_TONE_FLOOR, gt=0, description="prior=edges: the tone weights' floor, "
                                   "relative to the mean radiance")
    chroma_ls_factor: float = Field(CHROMA_LS_FACTOR, ge=0, description="prior=edges, known albedo, grey A (one "
                                    "albedo for all channels): the envmap's chroma (each channel over the channel "
                                    "mean) comes from a second edge solve at chroma_ls_factor x ls, its luminance "
                                    "(the channel mean) from the solve at ls (objcam.solvers.chroma: colour varies "
                                    "more slowly than brightness, and a dark channel otherwise clips to 0 in "
                                    "patches); 0: one solve for all channels")
    ls_noise_factor: float | None = Field(None, gt=0, description="ls from the relative noise sigma when ls is "
                                          "None (the target's noise_sigma, else estimated from the image): known "
                                          "albedo with prior=edges, ls = factor x sigma (None: "
                                          f"{EDGE_LS_PER_SIGMA:g}); otherwise (smooth, paper, the joint solve) "
                                          f"ls = factor x sigma^2 (None: {LS_NOISE_FACTOR:g})")
    texel_group: float | None = Field(
        None, ge=0, description="merge each lat-long row's texels into groups spanning at most texel_group x the "
        "equator texel's solid angle (objcam.solvers.basis: the same objective over envmaps constant on each "
        "group, written back on the lat-long grid); 0: one unknown per texel, the method's parameterisation. "
        f"None: {TEXEL_GROUP_KNOWN:g} for a known albedo, {TEXEL_GROUP_JOINT:.3g} for the joint solve "
        "(bench/results.md). method=adam always optimises the texels")
    lr: float = Field(DEFAULT_LR_REL, ge=0, description="L2 (ridge) weight, relative like ls")
    refine_fraction: float = Field(REFINE_FRACTION, ge=0, le=1, description="supersampled A "
                                   "(transport.supersample > 1), known albedo: the fraction of output texels, those "
                                   "of most contrast in a pilot solve, solved on A's finer grid "
                                   "(objcam.solvers.refine); the rest are one unknown each")
    lp: float | None = Field(None, ge=0, description="albedo smoothness weight (unknown albedo), relative to the "
                             f"albedo data term; None: 0 with >= 2 illuminations per camera, {LP_ONE_ILLUMINATION} "
                             "with one")
    auto_reg: Literal["gcv", "discrepancy", "lcurve", "off"] = Field(
        "off", description="rule choosing ls when ls is None (both albedo cases); off: the measured defaults "
        "(bench/results.md: on path-traced targets every rule picked far too little smoothing)")
    tol: float | None = Field(None, gt=0, description="joint solve: stop when the relative objective decrease per "
                              f"sweep is below tol; None: {JOINT_TOL:g}, or {JOINT_TOL_FINAL:g} when the final step "
                              "(final_envmap=known) follows")
    max_iter: int = Field(100, ge=1, description="joint solve: most sweeps (paper: most damped steps)")
    alpha: float = Field(0.5, gt=0, description="joint method=paper: damping of the envmap step (Eq. 7)")
    mixed_pixels: Literal["exclude", "fit"] = Field(
        "exclude", description="unknown albedo, method=exact: pixels whose footprint mixes the object and the support "
        "(silhouettes) are left out of the joint fit: one unknown albedo times A' cannot model a mixture whose "
        "effective albedo changes with the light (measured on the bench's dots scene: envmap SSIM 0.510 -> 0.543, "
        "and it is what lets the bounce refit help); 'fit' keeps them")
    bounce_refits: int = Field(1, ge=0, le=5, description="unknown albedo, method=exact: times the light the support "
                               "throws onto the object (interreflections, gathered at a guessed albedo by transport) "
                               "is redone from the estimated albedo and the joint solve rerun (objcam.transport."
                               "gather.bounce_delta; A with the gather's parts only). Measured on the dots scene: "
                               "envmap SSIM 0.543 -> 0.595, relative RMSE 0.87 -> 0.66, ~1.4x the solve time. 0: keep "
                               "the guess")
    first_solve_stride: int = Field(BOUNCE_FIRST_STRIDE, ge=1, le=8, description="unknown albedo with a bounce "
                                    "refit: the solve before the refit fits one pixel in stride x stride (with "
                                    "two or more illuminations; every pixel's albedo then follows from its least "
                                    "squares at that solve's envmaps); 1: every pixel")
    albedo_tv: float = Field(ALBEDO_TV, ge=0, description="unknown albedo, lp = 0, final_envmap=known: weight of the "
                             "total-variation albedo prior of the final step, as a contrast relative to the median "
                             "albedo (objcam.solvers.albedo_tv: variations below about it are flattened, a print's "
                             "edges stay); 0: off")
    final_rounds: int = Field(FINAL_ROUNDS, ge=1, le=10, description="final_envmap=known with albedo_tv: rounds of "
                              "(the albedo's TV step at the current envmaps, every envmap at that albedo)")
    final_envmap: Literal["known", "joint"] = Field(
        "known", description="unknown albedo, method=exact, prior=edges: 'known' follows the joint solve with "
        "final_rounds rounds of the albedo's TV step (albedo_tv) and every envmap at that albedo, held fixed, by "
        "the known-albedo solver (tone-weighted edge prior, edge_eps and ls as for a known albedo; measured on the "
        "dots bench scene: envmap SSIM 0.607 -> 0.710, 0.638 without the TV step); 'joint' keeps the joint "
        "solve's albedo and envmaps")
    adam_lr: float = Field(0.05, gt=0, description="method=adam: learning rate (on log radiance / logit albedo)")
    adam_seconds: float = Field(60.0, gt=0, description="method=adam: time budget (early stopping), seconds")
    adam_max_iter: int = Field(2000, ge=1, description="method=adam: most iterations")
    adam_spp: int = Field(4, ge=1, description="method=adam: samples per pixel of each differentiable render")
    adam_converge_tol: float = Field(1e-3, gt=0, description="method=adam: 'converged' when the learning rate is at "
                                     "its floor and 50 iterations improve the objective by less than this fraction "
                                     "(the benchmark's run to convergence uses 1e-5)")
    adam_patience: int = Field(2, ge=1, description="method=adam: windows of 25 iterations without that improvement "
                               "before the learning rate is halved (down to 1/16), then before it stops")
    adam_stop_on_plateau: bool = Field(True, description="method=adam: stop where the plateau rule fires "
                                       "('converged'); false records that time (plateau_seconds) and goes on at "
                                       "the smallest rate until adam_seconds (the benchmark's long run)")


# --------------------------------------------------------------------------------------------------- helpers


def _pixels(transport, image: np.ndarray, valid: np.ndarray):
    """The pooled target at A's rows: pooled (H', W', 3), ok (H', W'), y (M, 3) and usable (M,) bool."""
    from objcam.transport import pool_target

    img, ok = pool_target(image, valid, transport.downsample)
    y = img.reshape(-1, 3)[transport.pixel_index].astype(np.float64)
    use = ok.reshape(-1)[transport.pixel_index]
    return img, ok, y, use


def _texel_mask(grid: EnvGrid, texel_index: np.ndarray) -> np.ndarray:
    mask = np.zeros(grid.n_texels, bool)
    mask[texel_index] = True
    return mask.reshape(grid.shape)


def _write_target(d, env, mask, pooled, pooled_ok, pred, info, albedo=None, albedo_mask=None,
                  fine=None) -> None:
    """The per-target artifacts shared by every path (see the module docstring); ``fine``: (env, mask) on a
    supersampled A's grid, when env and mask are their area average."""
    resid = np.where(pooled_ok[..., None], pooled - pred, 0.0)
    if fine is not None:
        write_exr(d / "envmap_fine.exr", fine[0])
        write_png(d / "envmap_fine_mask.png", fine[1].astype(float))
    write_exr(d / "envmap.exr", env)
    write_png(d / "envmap_mask.png", mask.astype(float))
    write_exr(d / "prediction.exr", pred)
    write_exr(d / "residual.exr", resid)
    write_exr(d / "target.exr", pooled)
    write_tonemapped_png(d / "envmap.png", env)
    ref = write_tonemapped_png(d / "target.png", pooled)
    write_tonemapped_png(d / "prediction.png", pred, exposure_ref=ref)
    write_tonemapped_png(d / "residual.png", np.abs(resid), exposure_ref=ref)
    if albedo is not None:
        write_exr(d / "albedo.exr", albedo)
        write_png(d / "albedo.png", np.clip(albedo, 0, 1) ** (1 / 2.2))  # albedo is in [0, 1]: no exposure
        write_png(d / "albedo_mask.png", albedo_mask.astype(float))
    atomic_write_text(d / "solve.json", json.dumps(info, indent=2))


def _loaded(scene, transport_dir):
    """Per target: (Transport, pooled, pooled_ok, y (M, 3), use (M,)); one Transport per camera group."""
    from objcam.transport import load_transport
    from objcam.transport.storage import read_index

    index = read_index(transport_dir)
    by_group: dict[str, object] = {}
    out = {}
    for target in scene.targets:
        g = index["targets"].get(target.name)
        if g not in by_group:
            by_group[g] = load_transport(transport_dir, target.name)
        tr = by_group[g]
        image = target.load_image(scene.folder)
        valid = target.load_valid(scene.folder)
        pooled, ok, y, use = _pixels(tr, image, valid)
        if not use.any():
            raise StageError("no usable pixel sees the scene", scene.folder / target.image,
                             "check the camera pose and the valid mask")
        out[target.name] = (tr, pooled, ok, y, use)
    return out


# --------------------------------------------------------------------------------------------- known albedo


def _solve_known(scene, data, params: Params, out, names: list[str]) -> dict[str, dict]:
    from objcam import solvers

    per_target: dict[str, dict] = {}
    gram_cache: dict[tuple, np.ndarray] = {}
    rule = params.auto_reg if params.auto_reg != "off" else None
    lr = params.lr
    for name in names:
        target = scene.target(name)
        tr, pooled, pooled_ok, y, use = data[name]
        grid = EnvGrid(tr.env_height)
        C = tr.A.shape[0]
        t0 = time.perf_counter()
        X, kkt, obj, iters = np.zeros((tr.A.shape[2], 3)), np.zeros(3), np.zeros(3), 0
        grams = None
        auto_info = None
        with single_blas_thread():
            ls, ls_source = params.ls, "param"
            if ls is None:
                ls, ls_source = _noise_ls(target, pooled, pooled_ok, params, tr.downsample,
                                          linear=params.prior == "edges" and params.method == "exact",
                                          supersample=tr.env_height // tr.output_height)
            if rule is not None:
                # one weight for the target's channels: the criterion on the grey (channel-mean) transport
                Ag = tr.A[0][use] if C == 1 else tr.A[:, use].mean(axis=0)
                ls, _, inf = solvers.choose_weights(Ag, y[use], grid, tr.texel_index, rule=rule,
                                                    sigma=_sigma(target, y[use], rule), lr=lr)
                auto_info = {"rule": rule, "ls_relative": ls, "notes": inf["notes"],
                             "seconds": round(inf["seconds"], 3)}
                ls_source = f"auto_reg {rule}"
            if params.prior == "edges" and params.method == "exact":
                X, kkt, obj, iters, edge_info = _solve_edges(tr, grid, use, y, ls, lr, params)
                C = 0  # done: skip the quadratic loop below
            for c in range(C):
                # one Gram matrix per (A, channel, usable pixels, weights): shared by every channel of a grey A
                # and by every target that shares the camera and the valid mask
                key = (str(tr.folder), c, hash(use.tobytes()), ls, lr)
                Ac = tr.A[c] if use.all() else tr.A[c][use]  # a mask copies A's 16k x 1k floats
                if key not in gram_cache:
                    # the transport stage stored A^T A over all kept pixels; remove the few excluded rows
                    grams = tr.gram() if grams is None else grams
                    G = grams[c]
                    if not use.all():
                        G = G - solvers.gram(tr.A[c][~use])
                    ls_abs, lr_abs = solvers.absolute_weights(G, ls, lr)
                    D = solvers.difference_operator(grid, tr.texel_index)
                    Q = solvers.regularized_gram(G, D, ls_abs, lr_abs)
                    P = _known_basis(tr, params)
                    gram_cache[key] = (Q, None) if P is None else (merge_gram(P, Q), P)
                Q, P = gram_cache[key]
                chans = [0, 1, 2] if C == 1 else [c]
                Yc = y[use][:, chans]
                B = solvers.rhs(Ac, Yc, fast=True)
                if P is not None:  # the same objective over x = P z: P^T Q P, P^T b (objcam.solvers.basis)
                    B = np.asarray(P.T @ B)
                res = (solvers.solve_exact if params.method == "exact" else solvers.solve_paper)(Q, B)
                X[:, chans] = res.x if P is None else np.asarray(P @ res.x.reshape(P.shape[1], -1))
                kkt[chans], iters = res.kkt_residual, max(iters, res.iterations)
                obj[chans] = solvers.objective(Q, B, res.x, np.einsum("ij,ij->j", Yc, Yc))
        solve_s = time.perf_counter() - t0

        env = tr.envmap_from_x(X)
        mask = _texel_mask(grid, tr.texel_index)
        fine = None
        if tr.output_height != tr.env_height:  # supersampled A: write the area average (objcam.solvers.refine)
            fine = (env, mask)
            env, mask = average_to(env, mask, tr.output_height)
        pred = tr.predict(X)
        fit = pred.reshape(-1, 3)[tr.pixel_index][use]
        rel_res = float(np.linalg.norm(fit - y[use]) / max(np.linalg.norm(y[use]), 1e-30))
        info = {
            "method": params.method, "albedo": "known", "texels": int(len(tr.texel_index)),
            **_basis_info(tr.texel_index, _known_basis(tr, params), params, known=True),
            "pixels_used": int(use.sum()), "pixels_excluded": int((~use).sum()), "channels_in_A": int(C),
            "solve_seconds": round(solve_s, 4), "iterations": int(iters), "kkt_residual_max": float(kkt.max()),
            "objective": obj.tolist(), "relative_image_residual": rel_res, "ls_relative": ls, "lr_relative": lr,
            "ls_source": ls_source, "prior": params.prior if params.method == "exact" else "smooth",
        }
        if params.prior == "edges" and params.method == "exact":
            info["edges"] = edge_info
        if auto_info:
            info["auto_reg"] = auto_info
        if fine is not None:
            info["supersample"] = {"a_height": tr.env_height, "output_height": tr.output_height,
                                   **(edge_info.pop("refine", {}) if "edges" in info else {})}
        _write_target(out / name, env, mask, pooled, pooled_ok, pred, info, fine=fine)
        per_target[name] = info
    return per_target


def _texel_group(params: Params, known: bool) -> float:
    """The envmap basis' group size (objcam.solvers.basis) for this solve: 0 (texels) for method=adam."""
    if params.method == "adam":
        return 0.0
    if params.texel_group is not None:
        return float(params.texel_group)
    return TEXEL_GROUP_KNOWN if known else TEXEL_GROUP_JOINT


def _basis_info(texel_index: np.ndarray, P, params: Params, known: bool) -> dict:
    """solve.json's record of the envmap basis P over ``texel_index`` (objcam.solvers.basis; for a supersampled A
    the output-texel basis before refinement: the edge solve's refined count is in ``supersample``)."""
    return {"texel_group": _texel_group(params, known), "unknowns": unknowns(texel_index, P)}


def _known_basis(tr, params: Params, split: np.ndarray | None = None):
    """The known-albedo solve's basis P over A's texels (None: the texels): the merged basis
    (objcam.solvers.basis), or for a supersampled A the output texels with ``split`` of them refined
    (objcam.solvers.refine; None: none refined)."""
    g = _texel_group(params, known=True)
    if tr.output_height == tr.env_height:
        return texel_basis(tr.grid, tr.texel_index, g)
    if split is None:
        split = np.zeros(coarse_of(tr.grid, tr.texel_index, tr.output_height)[0].size, bool)
    return refined_basis(tr.grid, tr.texel_index, tr.output_height, split, g)


def _noise_ls(target, pooled: np.ndarray, pooled_ok: np.ndarray, params: Params, f: int = 1,
              linear: bool = False, supersample: int = 1) -> tuple[float, str]:
    """ls from the noise of one fitted pixel (the target's relative noise_sigma, given per photo pixel, over the
    f x f pooling; else estimated from the pooled image): ls_noise_factor x sigma^2, or x sigma when ``linear``
    (the known-albedo edge prior), within LS_RANGE (the noise sets how much the data can be trusted against the
    prior; measured on 128 x 128 targets, and transport's automatic pooling keeps larger photos at 8-32k fitted
    pixels)."""
    from objcam.transport.auto import estimate_relative_noise

    sigma, source = target.noise_sigma, "noise_sigma"
    if sigma:
        sigma = sigma / max(int(f), 1)  # the mean of f x f independent pixels
    else:
        sigma, source = estimate_relative_noise(pooled, pooled_ok), "estimated noise"
    if not sigma:
        return KNOWN_LS_REL, "default (noise unknown)"
    factor = params.ls_noise_factor
    if factor is None and linear:
        factor = EDGE_LS_PER_SIGMA if supersample == 1 else EDGE_LS_PER_SIGMA_SUPERSAMPLED
    elif factor is None:
        # a supersampled A (objcam.solvers.refine): mean diag(A^T A) shrinks ~s^4 and an output edge is s fine
        # edges, so s^3 keeps the output grid's weight (derived, not tuned: the bench measures the edge prior)
        factor = LS_NOISE_FACTOR * supersample**3
    ls = float(np.clip(factor * (sigma if linear else sigma**2), *LS_RANGE))
    return ls, f"{source} {sigma:.4f} per fitted pixel"


def _solve_edges(tr, grid: EnvGrid, use: np.ndarray, y: np.ndarray, ls: float, lr: float, params: Params):
    """Known albedo, edge-preserving prior (objcam.solvers.edges): X (N, 3), KKT, objective, steps, info."""
    from objcam import solvers
    from objcam.solvers.chroma import luminance_with_chroma
    from objcam.solvers.edges import solve_edges

    grams_all = tr.gram()
    C = tr.A.shape[0]
    grams, rhs, chans = [], [], []
    Y = y[use]
    for c in range(C):
        G = grams_all[c]
        if not use.all():
            G = G - solvers.gram(tr.A[c][~use])
        ch = [0, 1, 2] if C == 1 else [c]
        grams.append(G)
        rhs.append(solvers.rhs(tr.A[c] if use.all() else tr.A[c][use], Y[:, ch], fast=True))
        chans.append(ch)
    G_ref = grams[0] if C == 1 else sum(grams) / C
    ls_abs, lr_abs = solvers.absolute_weights(G_ref, ls, lr)
    D = solvers.difference_operator(grid, tr.texel_index)
    eps = params.edge_eps if params.edge_eps is not None else EDGE_EPS_KNOWN
    yy = np.einsum("ij,ij->j", Y, Y)
    basis = _known_basis(tr, params)
    refine_info = None
    if tr.output_height != tr.env_height:
        # supersampled A (objcam.solvers.refine): a pilot quadratic solve on the output texels says where the
        # envmap has contrast; those output texels are solved on the fine grid
        pilot = solve_edges(grams, rhs, chans, yy, D, ls_abs, lr_abs, steps=0, basis=basis)
        split = split_by_contrast(contrast(grid, tr.texel_index, tr.output_height, pilot.x), params.refine_fraction)
        basis = _known_basis(tr, params, split)
        refine_info = {"refine_fraction": params.refine_fraction, "refined_output_texels": int(split.sum()),
                       "output_texels": int(split.size), "unknowns": int(basis.shape[1])}
    # the chroma solve (objcam.solvers.chroma) needs one A for every channel: the luminance of X is then A's own
    split = params.chroma_ls_factor > 0 and C == 1
    weights = [ls_abs]
    if split:
        weights.append(solvers.absolute_weights(G_ref, ls * params.chroma_ls_factor, lr)[0])

    def one(w: float):
        return solve_edges(grams, rhs, chans, yy, D, w, lr_abs, steps=params.edge_steps, eps_rel=eps,
                           tone=params.edge_tone, tone_floor=params.edge_tone_floor, basis=basis)

    runs = parallel_map(one, weights)  # independent solves: a thread each (the caller holds one BLAS thread)
    res = runs[0]
    kkt = np.zeros(3)
    iters = 0
    for run in runs:
        for r, ch in zip(run.results, chans):
            kkt[ch] = np.maximum(kkt[ch], r.kkt_residual)
            iters += r.iterations
    obj = np.full(3, res.objective_history[-1] / 3)
    hist = res.objective_history
    info = {"steps": res.steps, "objective_history": hist, "edge_scale": res.edge_scale, "edge_eps": eps,
            "tone": res.tone, "tone_floor": params.edge_tone_floor if res.tone > 0 else None,
            "edges_above_threshold": round(res.kept_edges, 4),
            "monotone": _non_increasing(hist)}
    if refine_info:
        info["refine"] = refine_info
    X = res.x
    if split:
        X = luminance_with_chroma(res.x, runs[1].x)
        hc = runs[1].objective_history
        info["chroma"] = {"ls_factor": params.chroma_ls_factor, "steps": runs[1].steps, "objective_history": hc,
                          "monotone": _non_increasing(hc),
                          "black_texels_per_channel_before": [int(v) for v in (res.x <= 0).sum(axis=0)],
                          "black_texels_per_channel": [int(v) for v in (X <= 0).sum(axis=0)]}
    elif params.chroma_ls_factor > 0:
        info["chroma"] = {"ls_factor": params.chroma_ls_factor, "skipped": "A differs per channel"}
    return X, kkt, obj, iters, info


def _non_increasing(history: list[float]) -> bool:
    """An objective history that never rises (to 1e-9 relative)."""
    return bool(all(b <= a * (1 + 1e-9) for a, b in zip(history, history[1:])))


def _sigma(target, y: np.ndarray, rule: str) -> float | None:
    """Absolute noise standard deviation of one pixel value for the discrepancy rule: the target's relative
    ``noise_sigma`` (capture.toml) times its median positive pixel value."""
    if rule != "discrepancy":
        return None
    if not target.noise_sigma:
        raise StageError(f"auto_reg=discrepancy needs the noise level of target {target.name!r}",
                         fix="give noise_sigma for the target in capture.toml, or use solve.auto_reg=gcv")
    pos = y[y > 0]
    return float(target.noise_sigma * (np.median(pos) if pos.size else 1.0))


# ------------------------------------------------------------------------------------------- unknown albedo


def _mixed_pixels(tr) -> np.ndarray:
    """(M,) bool: pixels whose sub-pixel samples see both the object and the support while some of the pixel's
    albedo is unknown. The joint model ``y = rho A' x`` gives a pixel one albedo; such a pixel is
    ``rho_obj A'_obj x + rho_sup A'_sup x``, whose ratio to A' x changes with the illumination, so no albedo fits
    it and what it cannot fit goes into the envmap (on the bench's dots scene its 163 silhouette pixels, 1% of
    the image, had a model error of 4% against 1.4% on the object)."""
    of = np.asarray(tr.object_fraction)
    return (of > 0) & (of < 1) & np.asarray(tr.unknown_albedo, bool)


def _solve_unknown(scene, data, params: Params, out, comp, tr_of_cam, names_of) -> dict[str, dict]:
    """One joint problem (component ``comp``); writes its targets' artifacts and returns their solve.json."""
    from objcam.solvers.assemble import grey_rho_free
    from objcam.solvers.jointauto import JointSetup, solve_joint_auto

    grid = EnvGrid(tr_of_cam[comp.cameras[0]].env_height)
    cams = []
    for cam in comp.cameras:
        tr = tr_of_cam[cam]
        tnames = [names_of[(cam, ill)] for ill in comp.illuminations]
        use = np.logical_and.reduce([data[t][4] for t in tnames])
        mixed = _mixed_pixels(tr) if params.method == "exact" and params.mixed_pixels == "exclude" else None
        n_mixed = int((use & mixed).sum()) if mixed is not None else 0
        if mixed is not None:
            use = use & ~mixed
        if not use.any():
            raise StageError(f"no pixel is usable in every target of the camera of {tnames[0]!r} "
                             f"({', '.join(tnames)})", scene.folder / scene.target(tnames[0]).image,
                             "check the valid masks and saturation levels of these targets")
        rows = np.flatnonzero(use)
        A = grey_rho_free(tr, rows, comp.texel_index)
        Y = np.stack([data[t][3][rows] for t in tnames], axis=1)  # (M, L, 3)
        # start known pixels at their known albedo and unknown ones mid-range
        rho0 = np.where(tr.unknown_albedo[rows, None], 0.5, np.clip(tr.albedo[rows], 1e-3, 1.0))
        # pixels of known albedo (the object's, given in capture.toml) are held at it: they pin the scale that
        # unknown albedo alone leaves free (measured on the bench's dots scene: envmap SSIM 0.46 -> 0.51,
        # absolute albedo error 19% -> 1.5%). The paper's damped steps estimate every pixel's albedo, as the
        # method does: held pixels made them diverge there (objective x10 by sweep 8, no scale step to follow)
        fixed = ~tr.unknown_albedo[rows] if params.method == "exact" else np.zeros(rows.size, bool)
        sig = [_sigma(scene.target(t), data[t][3][rows], params.auto_reg) for t in tnames]
        cams.append(dict(key=cam, tr=tr, rows=rows, A=A, Y=Y, rho0=rho0, fixed=fixed, targets=tnames, sigma=sig,
                         n_mixed=n_mixed))
    L = len(comp.illuminations)
    # one illumination and no pixel of known albedo: every pixel's albedo can explain its value alone, so the data
    # do not constrain the envmap (its shape then comes from the priors; measured: image residual 0.000, SSIM 0.13
    # on the e2e bench's unknown-albedo capture against 0.47 with the albedo given); no refit then (it measured
    # +12 s there for nothing)
    unconstrained = L == 1 and all(bool(c["tr"].unknown_albedo[c["rows"]].all()) for c in cams)
    # the albedo's TV step and the envmaps at that albedo follow the joint solve (_final_step)
    final_step = (params.final_envmap == "known" and params.method == "exact" and params.prior == "edges"
                  and not unconstrained)
    tol = params.tol if params.tol is not None else (JOINT_TOL_FINAL if final_step else JOINT_TOL)
    # the joint solve's weights are relative to A' (albedo 1); ls and lr are relative to A = diag(rho0) A', as for
    # a known albedo, so one number means one prior strength in both cases
    num = sum(float(np.sum((c["rho0"] ** 2).mean(axis=1) @ (c["A"].astype(np.float64) ** 2))) for c in cams)
    den = sum(float(np.sum(np.einsum("mn,mn->n", c["A"], c["A"], dtype=np.float64))) for c in cams)
    conv = num / den if den > 0 else 1.0
    # ls when not given and auto_reg is off: from the targets' noise, as for a known albedo (median over the
    # problem's targets); measured near the best envmap SSIM on the 3-illumination bench scene (bench/results.md)
    ls_source = "param"
    ls_fixed = params.ls
    if ls_fixed is None and params.auto_reg == "off":
        got = [_noise_ls(scene.target(t), data[t][1], data[t][2], params, c["tr"].downsample)
               for c in cams for t in c["targets"]]
        ls_fixed = float(np.median([g[0] for g in got]))
        ls_source = f"median over the targets of {got[0][1].split(' ')[0]} ls ({len(got)} targets)"
    setup = JointSetup(
        method=params.method, prior=params.prior if params.method == "exact" else "smooth",
        edge_eps=params.edge_eps if params.edge_eps is not None else EDGE_EPS_JOINT,
        edge_steps=min(params.edge_steps, JOINT_EDGE_STEPS),
        ls=None if params.auto_reg != "off" else ls_fixed * conv, lr=params.lr * conv,
        lp=(0.0 if L >= 2 else LP_ONE_ILLUMINATION) if params.lp is None else params.lp,
        rule=params.auto_reg, ls0=JOINT_LS0_REL, tol=tol, max_iter=params.max_iter,
        alpha=params.alpha, texel_group=_texel_group(params, known=False))
    sigma = [s for c in cams for s in c["sigma"] if s is not None] or None

    def solve(rho, stp):
        """The joint solve of this problem's cameras (their current A') from the albedo ``rho`` (one per camera)."""
        return solve_joint_auto([(c["A"], c["Y"], c["tr"].pixel_index[c["rows"]], c["tr"].image_shape, r,
                                  c["fixed"]) for c, r in zip(cams, rho)], grid, comp.texel_index, stp, sigma=sigma)

    t0 = time.perf_counter()
    if final_step:  # its envmaps replace the joint solve's: no final exact x-step there
        setup = dataclasses.replace(setup, polish=False)
    refit_next = (params.bounce_refits > 0 and params.method == "exact" and not unconstrained
                  and any(c["tr"].has_bounce_parts for c in cams))
    # a bounce refit follows: the first solve only has to get the albedo close (its final decimals are redone), so
    # it stops early, with the quadratic prior (one factorisation per channel serves every target, no
    # majorise-minimise steps) and without the final float64 x-step. Measured on the dots bench scene: first solve
    # 25.5 -> 11.2 s, the stage 46 -> 33 s, envmap SSIM 0.597 -> 0.601 (bench/results.md)
    first = (dataclasses.replace(setup, tol=max(setup.tol, BOUNCE_FIRST_TOL), prior="smooth", polish=False)
             if refit_next else setup)
    stride = params.first_solve_stride if refit_next and L >= 2 and setup.lp == 0 else 1
    subs = _subsample(cams, stride) if stride > 1 else None
    if subs is not None and sum(s.size for s in subs) < max(64, comp.texel_index.size):
        stride, subs = 1, None  # too few pixels left to fit: every pixel
    if subs is not None:
        res, auto, first_pixels = _solve_subsampled(cams, subs, grid, comp.texel_index, first, sigma)
    else:
        res, auto = solve([c["rho0"] for c in cams], first)
        first_pixels = sum(int(c["rows"].size) for c in cams)
    # the support's light on the object was gathered at a guessed albedo: redo it from the estimate, solve again
    refits: list[dict] = []
    first_info = {"sweeps": int(res.iterations), "seconds": round(time.perf_counter() - t0, 3),
                  "objective": float(np.sum(res.objective)), "prior": first.prior, "tol": first.tol,
                  "pixel_stride": stride, "pixels": first_pixels}
    n_refits = params.bounce_refits if refit_next else 0
    loose = first is not setup  # res comes from a solve stopped early (a refit was to follow)
    for i in range(n_refits):
        t1 = time.perf_counter()
        more = _refit_bounce(cams, comp, res, params)
        for r in more:
            r["seconds"] = round(time.perf_counter() - t1, 3)
            r["first_solve"] = first_info
        if not more:
            break
        # every solve but the last one stops early too: another refit redoes its final decimals
        step = first if i < n_refits - 1 else setup
        res, auto = solve(res.rho, step)
        loose = step is not setup
        for r in more:
            r["objective_after"] = float(np.sum(res.objective))
        refits += more
    if loose and not res.diverged:
        # the last solve stopped early for a refit that found no cell to redo: finish it at the requested tol
        res, auto = solve(res.rho, setup)
    final_info = None
    if final_step and not res.diverged:
        # the albedo's edge-preserving step and each envmap once more by the known-albedo solver (_final_step)
        t1 = time.perf_counter()
        # a weight chosen by auto_reg carries over; else the known-albedo rule's (from the noise)
        ls_rule = float(res.info["ls_rel"]) / conv if auto is not None else None
        X_final, rho_final, final_info = _final_step(scene, data, cams, res, grid, comp.texel_index, params,
                                                     ls_rule, tv=setup.lp == 0)
        final_info["seconds"] = round(time.perf_counter() - t1, 3)
        res = dataclasses.replace(res, x=X_final, rho=rho_final)
    solve_s = time.perf_counter() - t0
    # a diverging iteration (only the paper's damped steps can: the exact alternation is monotone) is stopped by
    # the solver, which returns the best estimate it saw: that is what is written, marked diverged, and the stage
    # summary says so in one line (run() below)

    mask = _texel_mask(grid, comp.texel_index)
    n_held = int(sum(int(c["fixed"].sum()) for c in cams))  # pixels held at their known albedo
    per_target: dict[str, dict] = {}
    for p, c in enumerate(cams):
        tr, rows = c["tr"], c["rows"]
        rho = res.rho[p]  # (M_used, 3)
        hw = tr.image_shape[0] * tr.image_shape[1]
        alb = np.zeros((hw, 3), np.float32)
        alb[tr.pixel_index[rows]] = rho
        alb_mask = np.zeros(hw, bool)
        alb_mask[tr.pixel_index[rows][tr.unknown_albedo[rows]]] = True
        basis_info = _basis_info(comp.texel_index, texel_basis(grid, comp.texel_index, _texel_group(params, False)),
                                 params, known=False)
        for l, (ill, name) in enumerate(zip(comp.illuminations, c["targets"])):
            x = res.x[:, l, :]  # (N_union, 3)
            env = np.zeros((grid.n_texels, 3), np.float32)
            env[comp.texel_index] = x
            env = env.reshape(grid.height, grid.width, 3)
            fit = rho * (c["A"].astype(np.float64) @ x)  # (M_used, 3)
            pred = np.zeros((hw, 3), np.float32)
            pred[tr.pixel_index[rows]] = fit
            pooled, pooled_ok = data[name][1], data[name][2]
            yv = c["Y"][:, l, :]
            rel_res = float(np.linalg.norm(fit - yv) / max(np.linalg.norm(yv), 1e-30))
            info = {
                "method": params.method, "albedo": "unknown", "scale_ambiguous": bool(res.scale_ambiguous),
                "note": SCALE_NOTE if res.scale_ambiguous else SCALE_PINNED_NOTE,
                "pixels_albedo_known": n_held,
                "illumination": ill, "cameras_in_problem": len(cams), "illuminations_in_problem": L,
                "targets_in_problem": [t for cc in cams for t in cc["targets"]],
                "texels": int(comp.texel_index.size), **basis_info,
                "pixels_used": int(rows.size),
                "pixels_excluded": int(tr.pixel_index.size - rows.size),
                "pixels_excluded_mixed": c["n_mixed"],
                "pixels_albedo_estimated": int(alb_mask.sum()),
                "solve_seconds": round(solve_s, 4), "iterations": int(res.iterations),
                "converged": bool(res.converged), "message": res.message,
                "kkt_residual_max": final_info["kkt_residual_max"] if final_info else float(np.max(res.kkt_x)),
                "kkt_residual_albedo_max": float(np.max(res.kkt_rho)),
                "objective": res.objective.tolist(), "objective_history": [float(v) for v in res.history],
                "objective_step_history": [float(v) for v in res.step_history],
                "relative_image_residual": rel_res,
                "ls_relative": float(res.info["ls_rel"]) / conv, "lr_relative": float(res.info["lr_rel"]) / conv,
                "ls_source": ls_source if auto is None else f"auto_reg {params.auto_reg}",
                "ls_relative_to_rho_free_A": float(res.info["ls_rel"]),
                "lp_relative": float(res.info["lp_rel"]), "scale_at_clip": [bool(v) for v in res.scale_at_clip],
                "auto_reg": auto, "prior": res.info["prior"], "diverged": bool(res.diverged),
                "envmap_constrained_by_data": not unconstrained, "bounce_refits": refits,
                "final_envmap": final_info,
                "objective_monotone": bool(np.all(np.diff(res.step_history) <= 1e-12 * np.abs(
                    np.asarray(res.step_history[:-1])))) if params.method == "exact" else None,
                "solver": {k: res.info[k] for k in (
                    "grams", "gram_seconds", "x_step_seconds", "gn_seconds", "scale_seconds", "rho_step_seconds",
                    "mm_steps", "edge_scale", "edge_eps", "edges_above_threshold", "anderson_accepted",
                    "gn_accepted") if k in res.info},
            }
            _write_target(out / name, env, mask, pooled, pooled_ok, pred.reshape(*tr.image_shape, 3), info,
                          albedo=alb.reshape(*tr.image_shape, 3), albedo_mask=alb_mask.reshape(tr.image_shape))
            per_target[name] = info
    return per_target


def _final_step(scene, data, cams: list[dict], res, grid: EnvGrid, texel_index: np.ndarray, params: Params,
                ls_rule: float | None, tv: bool):
    """After the joint solve: ``final_rounds`` rounds of the albedo's edge-preserving step at the current envmaps
    (objcam.solvers.albedo_tv, when ``tv`` and ``albedo_tv`` > 0: the exact albedo step with a TV prior; lp = 0
    only, where the joint solve's albedo is each pixel's least squares) and every envmap at that albedo by the
    known-albedo solver (:func:`_final_envmaps`). Without the TV step, one round at the joint solve's albedo.
    Returns (X (N, L, 3), rho (list per camera of (M_p, 3)), info for solve.json)."""
    from objcam.solvers.albedo_tv import tv_albedo

    tv = tv and params.albedo_tv > 0
    if ls_rule is not None:
        ls, source = ls_rule, f"auto_reg {params.auto_reg}"
    elif params.ls is not None:
        ls, source = params.ls, "param"
    else:  # the known-albedo rule, the median over the problem's targets
        got = [_noise_ls(scene.target(t), data[t][1], data[t][2], params, c["tr"].downsample, linear=True)
               for c in cams for t in c["targets"]]
        ls, source = float(np.median([g[0] for g in got])), f"median over the targets of {got[0][1]}"
    X, rho = res.x, [np.asarray(r, np.float64) for r in res.rho]
    warm: list = [None] * len(cams)
    info: dict = {}
    rounds = params.final_rounds if tv else 1
    for k in range(rounds):
        if tv:
            for p, c in enumerate(cams):
                warm[p] = tv_albedo(c["A"], c["Y"], X, rho[p], c["fixed"], c["tr"].pixel_index[c["rows"]],
                                    c["tr"].image_shape, params.albedo_tv, warm=warm[p])
                rho[p] = warm[p].rho
        # a round's envmaps only feed the next albedo step, except the last one's: fewer reweightings before it
        steps = params.edge_steps if k == rounds - 1 else min(params.edge_steps, FINAL_EARLY_STEPS)
        X, info = _final_envmaps(cams, rho, grid, texel_index, params, ls, steps)
    info["ls_source"] = source
    info["rounds"] = rounds
    info["albedo_tv"] = ({"contrast": params.albedo_tv, "lam": [t.lam for t in warm],
                          "iterations": [t.iterations for t in warm], "edges": [t.edges for t in warm],
                          "regions": [t.regions for t in warm]}
                         if tv else None)
    return X, rho, info


def _final_envmaps(cams: list[dict], rhos: list[np.ndarray], grid: EnvGrid, texel_index: np.ndarray,
                   params: Params, ls: float, steps: int | None = None):
    """Every illumination's envmap at the albedo ``rhos`` (per camera (M_p, 3)), held fixed: the known-albedo
    solve (:func:`_solve_edges`' prior: tone-weighted edges at the relative weight ``ls``, its basis; ``steps``
    reweightings, None: params.edge_steps) of ``y_lc = diag(rho_pc) A'_p x_lc`` stacked over the problem's
    cameras. One Gram matrix per channel serves every illumination. Returns (X (N, L, 3), info for solve.json)."""
    from objcam import solvers
    from objcam.solvers.edges import solve_edges
    from objcam.solvers.joint import weighted_gram

    L, n = cams[0]["Y"].shape[1], texel_index.size
    rhos = [np.asarray(r, np.float64) for r in rhos]  # (M_p, 3)
    grams = [weighted_gram([c["A"] for c in cams], [r[:, ch] ** 2 for r in rhos], n, fast=True) for ch in range(3)]
    rhs = np.zeros((n, L, 3))
    yy = np.zeros((L, 3))
    for c, rho in zip(cams, rhos):
        W = (rho[:, None, :] * c["Y"]).reshape(rho.shape[0], -1)  # (M, L * 3): rho_c y_lc
        rhs += solvers.rhs(c["A"], W, fast=True).reshape(n, L, 3)
        yy += np.einsum("mlc,mlc->lc", c["Y"], c["Y"])
    with single_blas_thread():
        ls_abs, lr_abs = solvers.absolute_weights(sum(grams) / 3, ls, params.lr)
        D = solvers.difference_operator(grid, texel_index)
        eps = params.edge_eps if params.edge_eps is not None else EDGE_EPS_KNOWN
        P = texel_basis(grid, texel_index, _texel_group(params, known=True))
        X = np.zeros((n, L, 3))
        kkt = np.zeros((L, 3))
        hist = []

        def one(l: int):  # the illuminations' solves are independent: a thread per core (LAPACK releases the GIL)
            return solve_edges(grams, [rhs[:, l, ch:ch + 1] for ch in range(3)], [[0], [1], [2]], yy[l], D, ls_abs,
                               lr_abs, steps=params.edge_steps if steps is None else steps, eps_rel=eps,
                               tone=params.edge_tone, tone_floor=params.edge_tone_floor, basis=P)

        for l, r in enumerate(parallel_map(one, range(L))):
            X[:, l, :] = r.x
            kkt[l] = [np.max(q.kkt_residual) for q in r.results]
            hist.append(r.objective_history)
    return X, {"ls_relative": ls, "prior": "edges", "edge_eps": eps, "tone": params.edge_tone,
               "texel_group": _texel_group(params, known=True), "kkt_residual_max": float(kkt.max()),
               "objective_history": hist}


def _subsample(cams: list[dict], stride: int) -> list[np.ndarray]:
    """Per camera, the positions (into its rows) of one pixel in ``stride`` x ``stride`` of the image grid, and of
    every pixel of known albedo."""
    subs = []
    for c in cams:
        pix = c["tr"].pixel_index[c["rows"]]
        w = c["tr"].image_shape[1]
        subs.append(np.flatnonzero((((pix // w) % stride == 0) & ((pix % w) % stride == 0)) | c["fixed"]))
    return subs


def _solve_subsampled(cams: list[dict], subs: list[np.ndarray], grid: EnvGrid, texel_index: np.ndarray, setup,
                      sigma):
    """The joint solve on the rows ``subs`` of each camera (:func:`_subsample`), then every pixel's albedo at its
    envmaps (:func:`objcam.solvers.joint.albedo_at`, the exact rho-step when lp = 0). Returns (result with rho for
    all rows, auto, pixels fitted)."""
    from objcam.solvers.joint import albedo_at
    from objcam.solvers.jointauto import solve_joint_auto

    blocks = [(c["A"][s], c["Y"][s], c["tr"].pixel_index[c["rows"]][s], c["tr"].image_shape, c["rho0"][s],
               c["fixed"][s]) for c, s in zip(cams, subs)]
    res, auto = solve_joint_auto(blocks, grid, texel_index, setup, sigma=sigma)
    rho = [albedo_at(c["A"], c["Y"], res.x, c["rho0"], c["fixed"]) for c in cams]
    return dataclasses.replace(res, rho=rho), auto, sum(int(s.size) for s in subs)


def _refit_bounce(cams: list[dict], comp, res, params: Params) -> list[dict]:
    """Redo the interreflections of each camera's A' (in place) with the support's cells at the albedo the joint
    solve estimated over them (objcam.transport.gather.bounce_delta); returns one summary per camera changed
    (empty: nothing to redo, e.g. a direct-light A, the path-traced correction, or no cell seen)."""
    from objcam.transport.gather import bounce_delta

    if params.bounce_refits <= 0 or params.method != "exact" or res.diverged:
        return []
    out = []
    for p, c in enumerate(cams):
        tr = c["tr"]
        parts = tr.bounce_parts()
        if parts is None:
            continue
        # the joint albedo is known only up to one scale; the pixels of known albedo (the object, say) fix it for
        # the bounce, else its mean over the support stays at the transport's guess
        rows = c["rows"]
        rho = res.rho[p].mean(axis=1)
        known = ~tr.unknown_albedo[rows] & (rho > 0)
        if known.sum() >= 16:
            k = float(np.median(tr.albedo[rows][known].mean(axis=1) / rho[known]))
            how = f"median known/estimated albedo over {int(known.sum())} pixels"
        else:
            pn = parts["pixel_node"][rows]
            on = (pn >= 0) & tr.unknown_albedo[rows]
            guess = float(np.mean(parts["node_rho"][pn[on]].mean(axis=1))) if on.any() else 0.0
            k = guess / float(np.mean(rho[on])) if on.any() and np.mean(rho[on]) > 0 else 1.0
            how = "mean over the support kept at the transport's guess"
        dA, info = bounce_delta(parts, k * rho, rows)
        if dA is None:
            continue
        info.update(albedo_scale=k, albedo_scale_from=how)
        # A' = A / rho: the transport renders unknown albedo as 1, known pixels carry theirs
        alb = tr.albedo[rows].mean(axis=1)
        dA = dA / np.where(alb > 0, alb, 1.0)[:, None]
        own = np.asarray(tr.texel_index)
        # the delta is from the transport's guess: apply it to the A' as built, not to a previous refit's
        base = c.setdefault("A_built", c["A"].copy())
        if own.size == comp.texel_index.size and np.array_equal(own, comp.texel_index):
            c["A"] = np.ascontiguousarray(base + dA, dtype=np.float32)
        else:
            c["A"] = base.copy()
            c["A"][:, np.searchsorted(comp.texel_index, own)] += dA
        rel = float(np.linalg.norm(dA) / max(np.linalg.norm(c["A"]), 1e-30))
        out.append({"camera": p, **info, "relative_change_of_A": rel,
                    "objective_before": float(np.sum(res.objective))})
    return out


# ----------------------------------------------------------------------------------------------------- run


def run(inputs: StageInputs, params: Params) -> StageOutputs:
    from objcam.solvers.assemble import components

    scene = SceneArtifact.load(inputs.upstream["scene"])
    out = inputs.out
    t_all = time.perf_counter()
    data = _loaded(scene, inputs.upstream["transport"])
    if params.method == "adam" and any(tr.output_height != tr.env_height for tr, *_ in data.values()):
        # (an unknown albedo is refused by the transport stage, before it builds a supersampled A)
        raise StageError("a supersampled transport (transport.supersample) is solved by method exact or paper, "
                         "not method=adam", inputs.capture / "capture.toml", "set transport.supersample=1")
    if params.method == "adam":
        per_target = _solve_adam(scene, data, params, out)
    else:
        pairs = [(str(data[t.name][0].folder), getattr(t, "illumination", "") or t.name, t.name)
                 for t in scene.targets]
        try:
            comps = components(pairs)
        except ValueError as e:
            raise StageError(str(e), inputs.capture / "capture.toml",
                             "fix the targets' illumination names in capture.toml") from None
        tr_of_cam = {cam: data[t][0] for cam, _, t in pairs}
        names_of = {(cam, ill): t for cam, ill, t in pairs}
        per_target = {}
        for comp in comps:
            unknown = any(tr_of_cam[c].unknown_albedo.any() for c in comp.cameras)
            names = [names_of[(c, i)] for c in comp.cameras for i in comp.illuminations]
            if not unknown:
                per_target.update(_solve_known(scene, data, params, out, names))
                continue
            comp.texel_index = np.unique(np.concatenate([tr_of_cam[c].texel_index for c in comp.cameras]))
            per_target.update(_solve_unknown(scene, data, params, out, comp, tr_of_cam, names_of))
        per_target = {t.name: per_target[t.name] for t in scene.targets}
    total = time.perf_counter() - t_all
    worst_kkt = max(v["kkt_residual_max"] for v in per_target.values())
    joint = any(v.get("albedo") == "unknown" for v in per_target.values())
    ambiguous = any(bool(v.get("scale_ambiguous", True)) for v in per_target.values() if v.get("albedo") == "unknown")
    div = next((v for v in per_target.values() if v.get("diverged")), None)
    # every target repeats its camera's count once per illumination of its problem
    unk = [v for v in per_target.values() if v.get("albedo") == "unknown"]
    n_mixed = round(sum(v.get("pixels_excluded_mixed", 0) / max(v.get("illuminations_in_problem", 1), 1)
                        for v in unk))
    # bounce_refits holds one entry per refit and camera
    n_refit = max((len(v["bounce_refits"]) // max(len({r["camera"] for r in v["bounce_refits"]}), 1)
                   for v in unk if v.get("bounce_refits")), default=0)
    n_final = max(((v.get("final_envmap") or {}).get("rounds", 0) for v in unk), default=0)
    free = [k for k, v in per_target.items() if v.get("envmap_constrained_by_data") is False]
    summary = ((f"WARNING: joint solve ({params.method}) {div['message']}; fix: use solve.method=exact (monotone) "
                "or a smaller solve.alpha. " if div else "")
               + (f"WARNING: {', '.join(free)}: one illumination and every albedo unknown, so the albedo alone can "
                  "explain the photo and the envmap comes from the priors, not the data; fix: give the support's or "
                  "the object's albedo in capture.toml [albedo], or photograph two or more illuminations. "
                  if free else "")
               + f"{len(per_target)} target(s), {params.method}"
               + ((", joint albedo + envmap (envmap known only up to scale)" if ambiguous else
                   ", joint albedo + envmap (scale fixed by the pixels of known albedo)") if joint else "")
               + (f", {n_mixed} silhouette pixels left out" if n_mixed else "")
               + (f", support light redone {n_refit}x from the estimated albedo" if n_refit else "")
               + (f", final step: {n_final} round(s) of the albedo's TV step and the envmaps at it" if n_final else "")
               + f", {total:.2f} s; KKT residual <= {worst_kkt:.1e}; "
               + ", ".join(f"{k}: image residual {v['relative_image_residual']:.3f}" for k, v in per_target.items()))
    metrics = {"targets": per_target, "seconds": round(total, 4)}
    if joint:
        metrics["scale_ambiguous"] = ambiguous
    return StageOutputs(metrics=metrics, summary=summary)


def _solve_adam(scene, data, params: Params, out) -> dict[str, dict]:
    """method=adam: every target through objcam.solvers.adam (per camera group with unknown albedo)."""
    from objcam.solvers.adam import AdamSettings, solve_adam_targets

    settings = AdamSettings(lr=params.adam_lr, seconds=params.adam_seconds, max_iter=params.adam_max_iter,
                            spp=params.adam_spp, ls=params.ls if params.ls is not None else KNOWN_LS_REL,
                            lr_ridge=params.lr, lp=0.0 if params.lp is None else params.lp,
                            converge_tol=params.adam_converge_tol, patience=params.adam_patience,
                            stop_on_plateau=params.adam_stop_on_plateau)
    per_target: dict[str, dict] = {}
    for name, r in solve_adam_targets(scene, data, settings).items():
        tr, pooled, pooled_ok = data[name][0], data[name][1], data[name][2]
        grid = EnvGrid(tr.env_height)
        _write_target(out / name, r.envmap, _texel_mask(grid, tr.texel_index), pooled, pooled_ok, r.prediction,
                      r.info, albedo=r.albedo, albedo_mask=r.albedo_mask)
        per_target[name] = r.info
    return per_target
