"""End to end on a small synthetic scene: `objcam synth` then `objcam run` through the real CLI, with asserted
bounds against the known truth (sun direction, irradiance, relative RMSE, fit), the cache on a second run, and
exact vs paper. Every bound is also run on deliberately broken answers to the same scene, which must fail it
(tests/broken.py: a flat sky, the estimate rotated, a solve drowned in its prior, one shadow ray per pixel)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from objcam.envmap import EnvGrid, resample_to_height
from objcam.image_io import read_exr
from objcam.pipeline.cli import main


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("e2e") / "capture"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "256",
                 "--cameras", '[{"width": 64, "height": 64, "distance": 0.3}]']) == 0
    assert main(["run", str(cap), "--quiet", "--set", "transport.model=direct"]) == 0
    return cap


def irradiance(env: np.ndarray) -> np.ndarray:
    """(3,) irradiance on an upward-facing plane: sum of radiance x solid angle x cos(theta) over the sky."""
    g = EnvGrid(env.shape[0])
    w = g.solid_angles() * np.clip(g.directions()[..., 2], 0.0, None)
    return (env * w[..., None]).sum(axis=(0, 1))


def test_outputs_exist_and_are_consistent(capture):
    d = capture / "objcam" / "solve" / "t0"
    for name in ("envmap.exr", "envmap_mask.png", "prediction.exr", "residual.exr", "target.exr",
                 "envmap.png", "prediction.png", "residual.png", "target.png", "solve.json"):
        assert (d / name).is_file(), name
    env = read_exr(d / "envmap.exr")
    assert env.shape == (32, 64, 3)
    import cv2

    mask = cv2.imread(str(d / "envmap_mask.png"), cv2.IMREAD_UNCHANGED) > 127
    # texels below the plane's horizon light nothing visible: dropped, and reported as unsolved
    assert not mask[20:].any() and mask[:14].all()
    assert np.all(env[~mask] == 0)


# The accuracy bounds of this scene (sunrise, 64 x 64 px at 256 spp, direct A, 32 x 64 envmap), each between the
# default's measured value and the broken answers' (test_a_broken_answer_fails_the_bounds):
SUN_DEG = 6.0  # default 0.0 deg; a flat sky 82, the estimate turned 90 degrees 89
# default within 5.5% (the transport's point sources for the low sun; 1.6% with the narrow kernel it took before
# edge_tone 0.545, at relative RMSE 7.5 against 4.1 now); a flat sky of the truth's mean radiance 2.4x
IRRADIANCE_TOL = 0.08
# default 4.1 (7.5 at edge_tone 0.3); solve.ls=100 18.5, prior=smooth at ls=1 18.4, one shadow ray and one camera ray
# per pixel 14.9, a flat sky 18.8, the truth's row means 18.7, turned 90 degrees 24.0. (SSIM does not separate them
# here: the default scores 0.09, a flat sky 0.43 and the row-mean map 0.69, since the sun dominates the linear error
# and SSIM of the tonemapped maps rewards the smooth sky; bench/results.md reports both beside their baselines.)
REL_RMSE_MAX = 10.0


def truth32(capture: Path) -> np.ndarray:
    return resample_to_height(read_exr(capture / "truth" / "envmap.exr")[..., :3].astype(float), 32)


def missed_bounds(est: np.ndarray, mask: np.ndarray, truth: np.ndarray, residual: float | None = None,
                  noise_sigma: float | None = None) -> list[str]:
    """The accuracy bounds (above) that the envmap ``est`` (32, 64, 3) on its solved texels ``mask`` misses
    against ``truth``; with ``residual`` the solve's relative image residual against 3 sigma + 0.05 too."""
    from objcam.metrics import envmap_metrics

    m = envmap_metrics(est, truth, mask)
    ratio = irradiance(est) / irradiance(truth)
    missed = []
    if not m["brightest_angle_deg"] < SUN_DEG:
        missed.append("sun")
    if not np.all(np.abs(ratio - 1.0) < IRRADIANCE_TOL):
        missed.append("irradiance")
    if not m["relative_rmse"] < REL_RMSE_MAX:
        missed.append("relative_rmse")
    # the fit explains the image down to its noise plus the interreflections the direct model leaves out
    if residual is not None and not residual < 3 * noise_sigma + 0.05:
        missed.append("residual")
    return missed


def test_recovers_the_sun_the_irradiance_and_the_map(capture):
    from tests.broken import read_envmap

    metrics = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())["t0"]
    est, mask = read_envmap(capture / "objcam")
    assert missed_bounds(est, mask, truth32(capture)) == [], metrics
    assert metrics["relative_rmse"] < REL_RMSE_MAX  # evaluate scores the same map


# (broken answer, the bounds it must miss at least one of; measured)
BROKEN = {
    "flat sky of the truth's mean": ("sun", "irradiance", "relative_rmse"),  # 82 deg, 2.4x, 18.8
    "estimate turned 90 degrees": ("sun", "relative_rmse"),  # 89 deg, 24.0 (irradiance kept: it is a turn)
    "solve.ls=100": ("relative_rmse",),  # 18.5 (sun 4.2 deg and irradiance within 4.1%: both pass)
    "solve.ls=1e6": ("sun", "irradiance", "relative_rmse", "residual"),  # 77 deg, 1.14x, 18.8, residual 0.50
    "solve.prior=smooth, solve.ls=1": ("relative_rmse",),  # 18.4 (sun 2.4 deg, irradiance within 0.6%)
    "transport.samples=1, transport.subpixel_samples=1": ("relative_rmse",),  # 14.9 (sun 2.5, within 3%)
}


@pytest.mark.parametrize("broken", list(BROKEN))
def test_a_broken_answer_fails_the_bounds(capture, tmp_path, broken):
    """A test of the test: the bounds above, run on a broken answer to the same scene, are missed."""
    import tomllib

    from tests.broken import read_envmap, rerun, rotated, solve_info, truth_constant

    truth = truth32(capture)
    sigma = tomllib.loads((capture / "capture.toml").read_text())["targets"][0]["noise_sigma"]
    est, mask = read_envmap(capture / "objcam")
    residual = None
    if broken.startswith("flat"):
        est = truth_constant(truth, mask)
    elif broken.startswith("estimate turned"):
        est = rotated(est, mask, 90.0)
    else:
        sets = ["transport.model=direct"] + [s.strip() for s in broken.split(",")]
        work = rerun(capture, capture / "objcam", tmp_path / "work", sets)
        est, mask = read_envmap(work)
        residual = solve_info(work)["relative_image_residual"]
    missed = missed_bounds(est, mask, truth, residual, sigma)
    assert set(BROKEN[broken]) & set(missed), (broken, missed)


def test_evaluate_reports_the_baselines_beside_each_score(capture):
    import cv2

    from objcam.baselines import baseline_metrics
    from objcam.metrics import envmap_metrics

    metrics = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())["t0"]
    d = capture / "objcam" / "solve" / "t0"
    est = read_exr(d / "envmap.exr")[..., :3].astype(float)
    mask = cv2.imread(str(d / "envmap_mask.png"), cv2.IMREAD_UNCHANGED) > 127
    truth = resample_to_height(read_exr(capture / "truth" / "envmap.exr")[..., :3].astype(float), 32)
    # the existing keys keep their values; the baselines are the truth's constant and row-mean maps on that mask
    plain = envmap_metrics(est, truth, mask)
    for k in ("ssim", "tonemapped_rmse", "relative_rmse"):
        assert metrics[k] == pytest.approx(plain[k], rel=1e-9)
    base = baseline_metrics(truth, mask)
    for b in ("constant", "row_mean"):
        assert metrics["baselines"][b]["ssim"] == pytest.approx(base[b]["ssim"], rel=1e-9)
        assert metrics["skill"][f"ssim_over_{b}"] == pytest.approx(metrics["ssim"] - base[b]["ssim"], abs=1e-9)
    assert metrics["beats_row_mean"]["ssim"] == (metrics["ssim"] > base["row_mean"]["ssim"])


def test_solve_is_exact_and_fits_the_image(capture):
    from tests.broken import read_envmap

    info = json.loads((capture / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert info["kkt_residual_max"] < 1e-8
    truth = json.loads((capture / "truth" / "truth.json").read_text())["targets"]["t0"]
    # the fit explains the image down to its noise plus the interreflections the direct model leaves out (measured
    # 0.066 against 0.133; solve.ls=1e6 leaves 0.50: test_a_broken_answer_fails_the_bounds)
    est, mask = read_envmap(capture / "objcam")
    assert "residual" not in missed_bounds(est, mask, truth32(capture), info["relative_image_residual"],
                                           truth["noise_sigma"])


def test_second_run_is_cached_and_status_done(capture, capsys):
    assert main(["run", str(capture), "--quiet", "--set", "transport.model=direct"]) == 0
    out = capsys.readouterr().out
    assert out.count("skipped (unchanged)") == 6
    assert main(["status", str(capture), "--set", "transport.model=direct"]) == 0
    assert capsys.readouterr().out.count("done") >= 6


def test_exact_never_worse_than_paper(capture, tmp_path):
    # the same objective (the quadratic prior at the same weights) minimised by both methods
    runs = {}
    for method in ("exact", "paper"):
        work = tmp_path / method
        assert main(["run", str(capture), "--quiet", "--work", str(work), "--until", "solve",
                     "--set", "transport.model=direct", "--set", f"solve.method={method}",
                     "--set", "solve.prior=smooth"]) == 0
        runs[method] = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    exact, paper = runs["exact"], runs["paper"]
    assert exact["ls_relative"] == paper["ls_relative"] and exact["prior"] == paper["prior"] == "smooth"
    assert np.all(np.array(exact["objective"]) <= np.array(paper["objective"]) * (1 + 1e-9))
    assert paper["kkt_residual_max"] > exact["kkt_residual_max"]


def test_noise_rules_set_ls(capture, tmp_path):
    """The default (edge prior) takes ls = 1.5 sigma, the quadratic prior 300 sigma^2, sigma the target's
    noise_sigma (one fitted pixel: the transport does not pool this 64 x 64 target)."""
    from objcam.solvers.plan.defaults import EDGE_LS_PER_SIGMA, EDGE_TONE, LS_NOISE_FACTOR, LS_RANGE
    import tomllib

    sigma = tomllib.loads((capture / "capture.toml").read_text())["targets"][0]["noise_sigma"]
    edges = json.loads((capture / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert edges["prior"] == "edges" and "noise_sigma" in edges["ls_source"]
    assert edges["ls_relative"] == pytest.approx(float(np.clip(EDGE_LS_PER_SIGMA * sigma, *LS_RANGE)))
    assert edges["edges"]["tone"] == pytest.approx(EDGE_TONE) and edges["edges"]["edge_eps"] == 0.001
    work = tmp_path / "smooth"
    assert main(["run", str(capture), "--quiet", "--work", str(work), "--until", "solve",
                 "--set", "transport.model=direct", "--set", "solve.prior=smooth"]) == 0
    smooth = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    assert smooth["ls_relative"] == pytest.approx(float(np.clip(LS_NOISE_FACTOR * sigma**2, *LS_RANGE)))


def test_chroma_from_a_smoother_solve(capture, tmp_path):
    """The default takes the envmap's chroma from a second solve at CHROMA_LS_FACTOR x ls and its luminance from
    the solve at ls: the channel mean is exactly that of the one-solve estimate (chroma_ls_factor=0)."""
    from objcam.solvers.plan.defaults import CHROMA_LS_FACTOR

    d = capture / "objcam" / "solve" / "t0"
    info = json.loads((d / "solve.json").read_text())
    chroma = info["edges"]["chroma"]
    assert chroma["ls_factor"] == CHROMA_LS_FACTOR and chroma["monotone"]
    assert sum(chroma["black_texels_per_channel"]) <= sum(chroma["black_texels_per_channel_before"])
    work = tmp_path / "one"
    assert main(["run", str(capture), "--quiet", "--work", str(work), "--until", "solve",
                 "--set", "transport.model=direct", "--set", "solve.chroma_ls_factor=0"]) == 0
    one_info = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    assert "chroma" not in one_info["edges"] and one_info["ls_relative"] == info["ls_relative"]
    split = read_exr(d / "envmap.exr")[..., :3].astype(float)
    one = read_exr(work / "solve" / "t0" / "envmap.exr")[..., :3].astype(float)
    np.testing.assert_allclose(split.mean(-1), one.mean(-1), rtol=1e-5, atol=1e-7 * one.max())
    # the colour did change: the chroma solve is smoother
    assert np.abs(split - one).max() > 1e-3 * one.max()


def test_supersampled_transport(capture, tmp_path, capsys):
    """transport.supersample=2: A on the 64 x 128 grid, the solve on the adaptive basis (objcam.solvers.refine),
    envmap.exr area-averaged to the 32 x 64 asked for (envmap_fine.exr on A's grid); evaluate and analysis run on
    it (and the report), and it recovers the sun and the irradiance like the default."""
    import cv2
    import tomllib

    from objcam.solvers.refine import average_to
    from objcam.solvers.plan.defaults import EDGE_LS_PER_SIGMA_SUPERSAMPLED, LS_RANGE, REFINE_FRACTION

    work = tmp_path / "ss"
    assert main(["run", str(capture), "--quiet", "--work", str(work),
                 "--set", "transport.model=direct", "--set", "transport.supersample=2"]) == 0
    d = work / "solve" / "t0"
    env, fine = read_exr(d / "envmap.exr")[..., :3], read_exr(d / "envmap_fine.exr")[..., :3]
    mask = cv2.imread(str(d / "envmap_mask.png"), cv2.IMREAD_UNCHANGED) > 127
    fmask = cv2.imread(str(d / "envmap_fine_mask.png"), cv2.IMREAD_UNCHANGED) > 127
    assert env.shape == (32, 64, 3) and fine.shape == (64, 128, 3)
    avg, avg_mask = average_to(fine.astype(np.float64), fmask, 32)
    np.testing.assert_allclose(env, avg, rtol=1e-5, atol=1e-6 * float(avg.max()))
    assert np.array_equal(mask, avg_mask) and not mask[20:].any() and mask[:14].all()
    info = json.loads((d / "solve.json").read_text())
    ss = info["supersample"]
    assert ss["a_height"] == 64 and ss["output_height"] == 32 and info["kkt_residual_max"] < 1e-8
    assert ss["refined_output_texels"] == round(REFINE_FRACTION * ss["output_texels"])
    assert ss["unknowns"] > info["unknowns"]  # the refined texels add unknowns to the output grid's
    sigma = tomllib.loads((capture / "capture.toml").read_text())["targets"][0]["noise_sigma"]
    assert info["ls_relative"] == pytest.approx(float(np.clip(EDGE_LS_PER_SIGMA_SUPERSAMPLED * sigma, *LS_RANGE)))
    metrics = json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]
    default = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())["t0"]
    # the default's bounds (sun, irradiance, relative RMSE), which the broken answers miss
    assert missed_bounds(env.astype(float), mask, truth32(capture)) == [], metrics
    # sunrise's sun inside one 32 x 64 texel: measured relative RMSE 5.38 against the default's 6.13, SSIM 0.160
    # against 0.186 (both low: 64 x 64 pixels at 256 spp, the direct A missing the interreflections; before the
    # noise model of issue 22 session 23, 5.79 / 6.96 and 0.156 / 0.167, before the outlier weighting 5.06 / 6.70
    # and 0.101 / 0.089: the brightness weights moved the default's SSIM more than the refined solve's)
    assert metrics["relative_rmse"] < 0.9 * default["relative_rmse"], (metrics, default)
    assert metrics["ssim"] > default["ssim"] - 0.04, (metrics["ssim"], default["ssim"])
    assert (work / "report" / "index.html").is_file()
    # Adam optimises the texels through the renderer: it has no adaptive basis, and says so in one line
    assert main(["run", str(capture), "--quiet", "--work", str(work), "--until", "solve", "--set",
                 "transport.model=direct", "--set", "transport.supersample=2", "--set", "solve.method=adam"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("objcam: error:") and "method=adam" in line and "transport.supersample=1" in line


def test_analysis_maps(capture):
    """Leverage, uncertainty, spectrum and Cook's distance of the scene: identities that must hold, and the
    method's qualitative finding that the horizon is resolved worse than mid elevations. Broken variants, asserted
    below: a flat uncertainty map, the precision written for the uncertainty."""
    d = capture / "objcam" / "analysis"
    info = json.loads((d / "analysis.json").read_text())
    cam = json.loads((capture / "objcam" / "transport" / "index.json").read_text())["targets"]["t0"]
    g = info["groups"][cam]  # cam0, or cam0k where the transport took the narrow kernel (objcam.transport.kernel)
    # trace of the ridge hat matrix: sum of leverages == sum s^2 / (s^2 + lr)
    assert g["leverage_sum"] == pytest.approx(g["ridge_dof"], rel=1e-6)
    assert 0 < g["leverage_max"] < 1
    assert 1 <= g["effective_rank"] <= g["texels"]
    for name in ("leverage.png", "uncertainty.png", "spectrum.png", "gains.png", "leverage.exr", "uncertainty.exr"):
        assert (d / cam / name).is_file(), name
    assert (d / "t0" / "cooks.png").is_file() and info["targets"]["t0"]["cooks_max"] > 0
    unc = read_exr(d / cam / "uncertainty.exr")[..., 0]
    assert _horizon_over_mid(unc) > 1.2  # measured 1.51 on this 64 x 64 scene (1.44 in an earlier session)
    # a test of the test (tests/broken.py), each missing the bound: a flat map (an uncertainty that ignores A: 1.0)
    # and the precision sqrt(diag(A^T A) + lr) written for the uncertainty (0.33). Not a variant: the
    # uncertainty blind to collinearity, 1 / sqrt(diag(A^T A) + lr), gives 4.09 and passes: on this scene the
    # horizon's weak (grazing) columns alone make it uncertain, so the bound checks the ordering, not its cause
    # (test_analysis.py's sphere toy, with unit-norm columns, is the check of the collinearity)
    from objcam.solvers import absolute_weights, gram
    from objcam.transport import load_transport

    tr = load_transport(capture / "objcam" / "transport", "t0")
    G = tr.gram()[0] if tr.channels == 1 else gram(tr.A.mean(axis=0))
    lr = absolute_weights(G, 0.0, 1e-4)[1]  # the analysis stage's default ridge
    precision = np.zeros(EnvGrid(tr.env_height).n_texels)
    precision[tr.texel_index] = np.sqrt(np.diag(G) + lr)
    for broken in ((unc > 0).astype(float), precision.reshape(EnvGrid(tr.env_height).shape)):
        assert not _horizon_over_mid(broken) > 1.2, _horizon_over_mid(broken)


def _horizon_over_mid(unc: np.ndarray) -> float:
    """Mean uncertainty of the solved texels 80-90 degrees from the zenith over that of those 30-60 degrees, in a
    lat-long map ``unc`` (H, 2H) (0 where unsolved)."""
    theta = np.degrees(EnvGrid(unc.shape[0]).centres()[0])
    horizon = unc[(theta > 80) & (theta < 90) & (unc > 0)]
    mid = unc[(theta > 30) & (theta < 60) & (unc > 0)]
    return float(horizon.mean() / mid.mean())
