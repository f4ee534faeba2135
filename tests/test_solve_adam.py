"""method=adam (gradient descent through Mitsuba's differentiable renderer) on a tiny known-albedo scene: the loss
falls, the time budget stops it, and the envmap it reaches fits the photo and points at the sun (bounds that too few
steps or a flat sky miss)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from objcam.image_io import read_exr
from objcam.pipeline.cli import main

RUN = ["transport.model=direct", "transport.env_height=8", "solve.method=adam", "solve.adam_seconds=300",
       "solve.adam_spp=2", "solve.adam_lr=0.1"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("adam") / "capture"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "64",
                 "--cameras", '[{"width": 32, "height": 32, "distance": 0.3}]']) == 0
    args = ["run", str(cap), "--quiet", "--until", "evaluate", "--set", "solve.adam_max_iter=30"]
    for s in RUN:
        args += ["--set", s]
    assert main(args) == 0
    return cap


# Adam's bounds after 30 steps, between its measured values and the broken runs' (test_a_broken_run_fails_the_bounds).
# Adam is the baseline, and at 30 steps its envmap is no better than the truth's row-mean map (SSIM 0.50 against
# 0.53, tonemapped RMSE 0.167 against 0.130; a flat sky scores SSIM 0.38), so SSIM is no bound here: the fit, the
# objective's fall and the sun are.
OBJECTIVE_DROP = 0.5  # the noise-free objective at the end over its start: measured 0.22; 5 steps 0.80, one step 0.94
RESIDUAL_MAX = 0.3  # measured 0.22 (5 steps 0.45, 10 steps 0.39); 0.94 when the render's known albedo was
# multiplied in a second time (x fitted to 1 / rho of the truth)
SUN_DEG = 45.0  # two 22.5-degree texels; measured 25 (34 in an earlier session); one step 72, a flat sky 79


def missed_fit(info: dict) -> list[str]:
    """The fit's bounds (above) that a solve's solve.json ``info`` misses."""
    # the rendered loss of a 2-spp image grows with the sun's render noise as the sun forms, so judge the run by
    # the noise-free objective (with A'), recorded at the start, every 25 iterations and at the end
    h = info["objective_history_transport"]
    print("adam: objective end / start", h[-1][1] / h[0][1], "residual", info["relative_image_residual"])
    missed = [] if h[-1][1] < OBJECTIVE_DROP * h[0][1] else ["objective"]
    return missed + ([] if info["relative_image_residual"] < RESIDUAL_MAX else ["residual"])


def missed_sun(m: dict) -> list[str]:
    """The sun's bound that evaluate's metrics ``m`` of a target miss."""
    return [] if m["brightest_angle_deg"] < SUN_DEG else ["sun"]


def test_objective_decreases_and_the_fit_is_close(capture):
    """The loss history, and the fit's bounds (missed_fit). Broken variants (test_a_broken_run_fails_the_bounds):
    5 steps, 1 step."""
    info = json.loads((capture / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert info["method"] == "adam" and info["stopped"] in ("max_iter", "converged")
    assert 20 <= len(info["loss_history"]) <= 30
    h = info["objective_history_transport"]
    assert h[0][0] == 0 and h[-1][0] == info["iterations"]
    # the prediction rho * A' x fits the photo and the noise-free objective fell
    assert missed_fit(info) == [], info["relative_image_residual"]


def test_result_fits_the_photo_and_points_at_the_sun(capture):
    """The fit and the sun. Broken variants (test_a_broken_run_fails_the_bounds): 5 steps, 1 step, a flat sky."""
    m = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())["t0"]
    info = json.loads((capture / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert missed_fit(info) + missed_sun(m) == [], (m, info["relative_image_residual"])


# (broken run, the bounds it must miss at least one of; measured)
BROKEN = {
    "solve.adam_max_iter=5": ("objective", "residual"),  # objective 0.80 of its start, residual 0.45 (sun 33)
    "solve.adam_max_iter=1": ("objective", "residual", "sun"),  # 0.94, 0.49, 72 deg
    "flat sky of the truth's mean": ("sun",),  # 79 deg (no solve: the sun alone decides)
}


@pytest.mark.parametrize("broken", list(BROKEN))
def test_a_broken_run_fails_the_bounds(capture, tmp_path, broken):
    """A test of the test (tests/broken.py): too few steps, or a flat sky, miss the bounds above."""
    from objcam.metrics import envmap_metrics
    from objcam.envmap import resample_to_height
    from tests.broken import read_envmap, rerun, solve_info, truth_constant

    w = capture / "objcam"
    if broken.startswith("flat"):
        env, mask = read_envmap(w)
        truth = resample_to_height(read_exr(capture / "truth" / "envmap.exr")[..., :3].astype(np.float64), 8)
        missed = missed_sun(envmap_metrics(truth_constant(truth, mask), truth, mask))
    else:
        w = rerun(capture, w, tmp_path / "work", RUN + [broken], until="evaluate")
        m = json.loads((w / "evaluate" / "metrics.json").read_text())["t0"]
        print(broken, "sun", m["brightest_angle_deg"])
        missed = missed_fit(solve_info(w)) + missed_sun(m)
    assert set(BROKEN[broken]) & set(missed), (broken, missed)


def test_time_budget_stops_it(capture):
    assert main(["run", str(capture), "--quiet", "--until", "solve", "--set", "transport.model=direct",
                 "--set", "transport.env_height=8", "--set", "solve.method=adam", "--set", "solve.adam_seconds=0.01",
                 "--set", "solve.adam_spp=2"]) == 0
    info = json.loads((capture / "objcam" / "solve" / "t0" / "solve.json").read_text())
    # checked before each iteration: a 10 ms budget stops it after the first one or two (an iteration takes ~8 ms
    # here, 25 in a 0.2 s budget; a fresh clone saw 2), far short of adam_max_iter (2,000), which an unchecked budget
    # would reach
    assert info["stopped"] == "time budget" and 1 <= info["iterations"] <= 5, info


def test_adam_objective_is_the_exact_solvers_objective(capture):
    """AdamProblem.objective (what Adam minimises, evaluated with A') equals the Gram-form objective the exact solver
    minimises at the same relative weights, and the exact minimiser scores below Adam's result on it."""
    from objcam import solvers
    from objcam.envmap import EnvGrid
    from objcam.envmap import read_latlong
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.solvers.adam import AdamProblem, AdamSettings
    from objcam.stages.solve import load_targets

    w = capture / "objcam"
    scene = SceneArtifact.load(w / "scene")
    data = load_targets(scene, w / "transport")
    ls_rel, lr_rel = 0.05, 1e-4
    pb = AdamProblem.build(data, ["t0"], AdamSettings(ls=ls_rel, lr_ridge=lr_rel))
    tr, y, use = data["t0"][0], data["t0"][3], data["t0"][4]
    A = np.asarray(tr.A[0], np.float64)[use]  # known grey albedo: A = diag(rho) A'
    G = A.T @ A
    ls_abs, lr_abs = solvers.absolute_weights(G, ls_rel, lr_rel)
    Q = solvers.regularized_gram(G, solvers.difference_operator(EnvGrid(tr.env_height), tr.texel_index), ls_abs,
                                 lr_abs)
    Y = y[use].astype(np.float64)
    B = A.T @ Y
    res = solvers.solve_exact(Q, B)
    x_opt = res.x.reshape(-1, 3)
    f_gram = float(np.sum(x_opt * (Q @ x_opt)) - 2 * np.sum(B * x_opt) + np.sum(Y * Y))
    f_opt = pb.objective(x_opt[None], pb.rho_known)
    assert f_opt == pytest.approx(f_gram, rel=1e-6)
    x_adam = tr.x_from_envmap(read_latlong(w / "solve" / "t0" / "envmap.exr")[..., :3]).astype(np.float64)
    f_adam = pb.objective(x_adam[None], pb.rho_known)
    # the exact minimiser is optimal for this function: below Adam's 30 steps and below nearby points
    assert f_opt < f_adam
    assert f_opt < pb.objective(1.05 * x_opt[None], pb.rho_known)
    assert f_opt < pb.objective(0.95 * x_opt[None], pb.rho_known)


def test_plateau_rule_can_record_and_go_on(capture, tmp_path):
    """stop_on_plateau=false (the benchmark's long run): where the plateau rule fires it records the iteration and
    the time and goes on at the smallest rate to max_iter; the stopping run ends there, on the same trajectory."""
    # box texels: this tests the plateau rule's bookkeeping; on the point-source A (transport.texel_kernel's
    # default pick here) the two runs' float32 render sums part by 1.6e-4 by iteration 150 (7e-7 on box texels)
    sets = ["--set", "transport.model=direct", "--set", "transport.env_height=8", "--set", "transport.texel_kernel=1",
            "--set", "solve.method=adam",
            "--set", "solve.adam_seconds=300", "--set", "solve.adam_spp=2", "--set", "solve.adam_lr=0.1",
            # every window of 25 iterations 'stalls' (99% improvement asked): halvings at 50..125, plateau at 150
            "--set", "solve.adam_converge_tol=0.99", "--set", "solve.adam_patience=1"]
    runs = {}
    for stop in ("true", "false"):
        work = tmp_path / stop
        assert main(["run", str(capture), "--quiet", "--until", "solve", "--work", str(work), *sets,
                     "--set", f"solve.adam_stop_on_plateau={stop}", "--set", "solve.adam_max_iter=175"]) == 0
        runs[stop] = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    stopped, went_on = runs["true"], runs["false"]
    assert stopped["stopped"] == "converged" and stopped["iterations"] == stopped["plateau_iteration"] == 150
    assert went_on["stopped"] == "max_iter" and went_on["iterations"] == 175 and went_on["plateau_iteration"] == 150
    assert went_on["lr_halved_at"] == stopped["lr_halved_at"] == [50, 75, 100, 125]
    assert 0 < went_on["plateau_seconds"] <= went_on["solve_seconds"]
    # the same seeds and steps up to the plateau: the same objective there (to the renderer's float32 sums, whose
    # order varies between runs: measured 7e-7 relative)
    h_stop, h_on = dict(map(tuple, stopped["objective_history_transport"])), dict(
        map(tuple, went_on["objective_history_transport"]))
    assert h_on[150] == pytest.approx(h_stop[150], rel=1e-4)
    assert len(went_on["objective_history_seconds"]) == len(went_on["objective_history_transport"])
