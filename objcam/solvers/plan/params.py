"""The solve's settings (the ``solve`` stage's params): one typed field per choice, each with its description.

The defaults and how each was measured are in :mod:`objcam.solvers.plan.defaults`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from objcam.solvers.plan.defaults import (
    ALBEDO_TV,
    ALBEDO_TV_FACTOR,
    ALBEDO_TV_TOP,
    BOUNCE_FIRST_STRIDE,
    CHROMA_LS_FACTOR,
    EDGE_EPS_JOINT,
    EDGE_EPS_KNOWN,
    EDGE_LS_PER_SIGMA,
    EDGE_TONE,
    EDGE_TONE_FLOOR,
    FINAL_ROUNDS,
    JOINT_TOL,
    JOINT_TOL_FINAL,
    JOINT_TOL_FINAL_ONE_ILLUMINATION,
    LP_ONE_ILLUMINATION,
    LR_SIGMA_REF,
    LS_NOISE_FACTOR,
    OUTLIER_K,
    REFINE_FRACTION,
    TEXEL_GROUP_JOINT,
    TEXEL_GROUP_KNOWN,
)
from objcam.solvers.regularization import DEFAULT_LR_REL


class SolveParams(BaseModel):
    """How the solve stage recovers the envmaps (and an unknown albedo); see objcam.solvers.plan."""

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
    lr: float | None = Field(
        None, ge=0, description="L2 (ridge) weight, relative like ls. None: for the known-albedo edge prior with ls "
        f"from the noise (a known albedo; an unknown one's final envmaps, at the targets' median), {DEFAULT_LR_REL:g} "
        f"x min(1, sigma / {LR_SIGMA_REF:g}) (the ridge follows the noise as ls does); elsewhere {DEFAULT_LR_REL:g}")
    weak_texels: Literal["keep", "exclude", "tie"] = Field(
        "exclude", description="known albedo, and the unknown albedo's final step (final_envmap=known, on its own "
        "A = diag(rho) A'): texels the photo barely sees (column norm under weak_fraction x the "
        "median above the horizon: the row below the horizon, seen past the support's edge through a sliver) -- "
        "'exclude': not solved, 0 and unmarked in envmap_mask.png; 'tie': each takes the value of the first "
        "well-seen texel above it in its column (objcam.solvers.basis.restrict_weak); 'keep': solved like the "
        "others. Measured (bench/results.md, session 14): exclude raises SSIM on both suites (hard median at 2% "
        "0.648 -> 0.685, core sunrise 0.723 -> 0.778) and ends the energy put below the horizon (up to 6.6x the "
        "truth's above it), at a cost in the 0-10 deg band's energy under high lamps; tie changes little")
    outliers: Literal["huber", "reject", "keep"] = Field(
        "huber", description="known albedo, prior=edges: pixels whose residual exceeds outlier_threshold x "
        "max(the stated noise, the residuals' robust spread), found after the first edge steps (again from a "
        "fresh solve without them when they bent that fit), are down-weighted to threshold / |residual| ('huber') or dropped ('reject') "
        "and the solve continues on the rest (fireflies, hot pixels, glints, geometry the model lacks: "
        "objcam.solvers.outliers; nothing is done past a tenth of the pixels); 'keep': plain least squares. "
        "Measured on the hard-case suite and the core bench (bench/results.md, issue 22)")
    sources: Literal["off", "compact"] = Field(
        "compact", description="known albedo, prior=edges: 'compact': after the solve and its sky profile, the "
        "light of each bright blob (texels above 10 x the map's median) is moved into the one texel of the blob "
        "that fits the photo best (or split with a neighbour where the photo says so), kept when the fit's "
        "misfit falls by at least a fifth of what the map misfits beyond the stated noise and no texel of the "
        "blob away from it fits nearly as well (objcam.solvers.sources: the edge prior spreads a small lamp the "
        "photo places); 'off': the map as solved")
    sky_profile: Literal["auto", "off"] = Field(
        "auto", description="known albedo, prior=edges: 'auto': after the solve, when the sky outside the bright "
        "blobs (texels above 10 x the map's median, grown by one texel) set to its mean per lat-long row raises the "
        "fit's misfit by less than its own chi-squared spread (or, failing that, the profile model's own fit on the "
        "same pixels misfits by at most that spread, or by the map's own misfit beyond the noise where larger, more "
        "than the map, and by at most the spread less unless the map's light is one bright blob over a sky), the "
        "envmap is solved again on that model, "
        "one unknown per row's sky texels (objcam.solvers.skyprofile: the edge prior draws azimuthal patches and dark "
        "rings into a dim sky that the photo barely sees beside a lamp or the sun), the rows' levels with the "
        "curvature of their profile in elevation added to the prior, and no source or rim left darker than its "
        "row's sky; 'off': the map as solved. "
        "Measured: bench/results.md, issues 22 and 28, sessions 29, 31, 33, 36 and 37")
    align: Literal["auto", "off"] = Field(
        "auto", description="'auto': after the solve, the shift (pixels of A's grid) that maps the model's image onto "
        "each camera's photos is estimated from the prediction's gradients; where it is significant (over 3 of its "
        "standard errors and 0.05 px) the photos are resampled by it and the capture solved again, up to 3 rounds, "
        "a round kept only when its solve removes a fifth of the misfit beyond the noise (model error leans on the "
        "gradients too) (objcam.solvers.plan.align: a camera pose a quarter of a pixel off cost the demo 0.36 SSIM); "
        "solve.json records the shift. 'off': the photos as posed")
    verdict: Literal["full", "fit"] = Field(
        "full", description="'full': every measure of the verdict (objcam.solvers.plan.verdict); 'fit': only the "
        "fit's (chi2, the residual, the black sky, the brightest source, the energy below the horizon), without "
        "the posterior's uncertainty and resolution (~0.1 s a target): what the transport's texel-kernel choice "
        "compares its pilot solves by")
    noise_fit: Literal["auto", "off"] = Field(
        "auto", description="known albedo, prior=edges, ls from the noise: 'auto': when the edge solve's residual is "
        "significantly below the stated (or estimated) noise (chi-squared per value under 1 - unknowns per channel / "
        "fitted pixels by more than 3 of its own spreads), the photo is less noisy than stated: the prior's weight "
        "and the outlier scale are set from the noise the residual supports (sigma x sqrt(chi2 / expected)) and the "
        "target solved again (objcam.solvers.plan.rules.noise_scale; the verdict still reports chi2 against the "
        "stated noise). "
        "Never raises the noise: a residual above it is model error, not noise. 'off': the stated noise as is")
    noise_model: Literal["brightness", "flat"] = Field(
        "brightness", description="known albedo, prior=edges, outliers huber or reject (keep is plain least squares, "
        "one noise): 'brightness': after the first edge steps the pixels are grouped by predicted brightness (bins a "
        "factor sqrt 2 wide) and a group whose residuals' robust spread, made non-decreasing in brightness, exceeds "
        "3x the median pixel's (OUTLIER_CLEAN_SPREAD: misfit beyond ordinary) is weighted down by the excess "
        "(objcam.solvers.outliers.brightness_weights): a bright object's shading the model lacks, a path tracer's "
        "noise on bright pixels. 'flat': one noise for every pixel. Measured (bench/results.md, issue 22 session "
        "23): hard-suite median SSIM 0.745 -> 0.788 at 0.5% noise, 0.740 -> 0.766 at 2% (37 targets better, 4 "
        "worse by at most 0.04), the core bench unchanged")
    outlier_threshold: float = Field(OUTLIER_K, gt=0, description="outliers=reject: the residual, in units of "
                                     "max(noise, robust spread), beyond which a pixel is dropped (6: a normal value "
                                     "exceeds it once in 5e8)")
    weak_fraction: float = Field(0.1, gt=0, lt=1, description="weak_texels: the column-norm fraction under which "
                                 "a texel counts as barely seen")
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
                              f"(final_envmap=known) follows ({JOINT_TOL_FINAL_ONE_ILLUMINATION:g} with lp > 0, "
                              "i.e. one illumination)")
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
    bounce_level: Literal["auto", "fit", "guess"] = Field(
        "auto", description="unknown albedo with a bounce refit and no pixel of known albedo: the support's albedo "
        "level the refitted interreflections use, which the joint solve's scale leaves free. 'fit': the level "
        "among BOUNCE_LEVELS (mean support albedo) whose solve has the lowest objective, refined by a parabola "
        "(the interreflections are the one part of the model that sees the albedo's absolute level); 'guess': "
        "the transport's guess (0.5); 'auto': fit where a surface is declared \"uniform\", else the guess (with "
        "an albedo per object pixel each absorbs the bounce's level and the fit chose 0.67-0.9 where one colour "
        "chose 0.5-0.8, worse on 5 of 21 targets: bench/results.md, session 50)")
    first_solve_stride: int = Field(BOUNCE_FIRST_STRIDE, ge=1, le=8, description="unknown albedo with a bounce "
                                    "refit: the solve before the refit fits one pixel in stride x stride (with "
                                    "two or more illuminations; every pixel's albedo then follows from its least "
                                    "squares at that solve's envmaps); 1: every pixel")
    albedo_tv: float = Field(ALBEDO_TV, ge=0, description="unknown albedo, lp = 0, final_envmap=known: weight of the "
                             "total-variation albedo prior of the final step, as a contrast relative to the median "
                             "albedo (objcam.solvers.albedo_tv: variations below about it are flattened, a print's "
                             "edges stay); with albedo_tv_rule=gcv the smallest contrast tried; 0: off")
    albedo_tv_rule: Literal["gcv", "fixed"] = Field(
        "gcv", description="how the final step's TV contrast is chosen: 'gcv' tries albedo_tv x "
        f"{ALBEDO_TV_FACTOR:g}^k up to {ALBEDO_TV_TOP:g} and keeps the one with the lowest generalised "
        "cross-validation score of the noise-weighted fit (objcam.solvers.albedo_gcv: a uniform support merges into "
        "one region, a print keeps its dots; measured on issue 29's family and the dots scene, bench/results.md); "
        "'fixed': albedo_tv as given")
    final_rounds: int = Field(FINAL_ROUNDS, ge=1, le=10, description="final_envmap=known with albedo_tv: rounds of "
                              "(the albedo's TV step at the current envmaps, every envmap at that albedo)")
    final_envmap: Literal["known", "joint"] = Field(
        "known", description="unknown albedo, method=exact, prior=edges: 'known' follows the joint solve with "
        "final_rounds rounds of the albedo's TV step (albedo_tv) and every envmap at that albedo, held fixed, by "
        "the known-albedo solver (tone-weighted edge prior, edge_eps and ls as for a known albedo; measured on the "
        "dots bench scene: envmap SSIM 0.607 -> 0.710, 0.638 without the TV step); 'joint' keeps the joint "
        "solve's albedo and envmaps")
    pinned_scale: bool = Field(True, description="unknown albedo with pixels of known albedo, method=exact: end the "
                               "joint solve on the scale those pixels' data alone choose (the envmap priors would "
                               "shrink it: on issue 29's dark object the support's albedo came out 5-18% bright); "
                               "false: the minimiser of the objective, scale and all")
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

    @property
    def ridge(self) -> float:
        """The relative ridge weight where no noise rule applies (the quadratic prior, the joint solve itself, the
        verdict's uncertainty): ``lr``, else the fixed default."""
        return DEFAULT_LR_REL if self.lr is None else self.lr
