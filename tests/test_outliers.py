"""Outlier pixels (issue 22): a few pixels far off the model (fireflies, hot pixels, glints) must not move the envmap.

Renderer-free scene (ground pixels under occluding spheres, tests/toy_scenes.py) with a known envmap: the photo
with a handful of pixels at 30-300x their value is solved with outliers dropped or down-weighted and compared
with the solve of the clean photo; ``outliers=keep`` (plain least squares) is the broken variant that must fail
the same bound.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from objcam.solvers.outliers import outlier_rows, robust_scale
from objcam.solvers.plan.params import SolveParams
from objcam.solvers.plan.targets import TargetData, TargetSolution
from objcam.solvers.plan.verdict import assess
from tests.toy_scenes import TOY_NOISE, solve_toy, sun_sky_toy

SIDE = 40
NOISE = TOY_NOISE


@pytest.fixture(scope="module")
def toy():
    tr, grid, _, clean = sun_sky_toy(side=SIDE)
    rng = np.random.default_rng(1)
    sigma_abs = NOISE * float(np.median(clean[clean > 0]))
    photo = clean + sigma_abs * rng.normal(size=clean.shape)
    hot = rng.choice(len(clean), 8, replace=False)
    bad = photo.copy()
    bad[hot] *= rng.uniform(30, 300, (8, 1))  # fireflies: a few pixels far brighter than the model allows
    return tr, grid, photo, bad, hot, sigma_abs


def _solve(tr, grid, y, sigma_abs, mode):
    return solve_toy(tr, grid, y, sigma_abs, outliers=mode)


def _error(X, ref):
    return float(np.linalg.norm(X - ref) / np.linalg.norm(ref))


def test_robust_scale_and_rows():
    rng = np.random.default_rng(0)
    r = rng.normal(0.0, 2.0, (5000, 3))
    assert robust_scale(r) == pytest.approx(2.0, rel=0.05)
    assert not robust_scale(1.1 * r) == pytest.approx(2.0, rel=0.05)  # a test of the test: 10% wider misses it
    y = r.copy()
    y[[10, 20, 30]] += 100.0  # three wild pixels (50x the spread)
    rows, rec = outlier_rows(y, np.zeros_like(y), sigma_abs=1.0, k=6.0, max_share=0.1)
    assert set(np.flatnonzero(rows)) == {10, 20, 30}
    assert rec["pixels"] == 3 and rec["robust_scale"] == pytest.approx(2.0, rel=0.05) and rec["chi2_share"] > 0.5
    # a test of the test (tests/broken.py): a plain standard deviation, which the three wild pixels inflate
    # (measured 3.2), misses the robust scale's bound
    assert not float(np.std(y)) == pytest.approx(2.0, rel=0.05)
    assert np.all(rec["weights"][rows] < 0.2) and np.all(rec["weights"][~rows] == 1.0)
    # a model wrong everywhere: more than max_share beyond the threshold drops nothing
    rows, rec = outlier_rows(y, np.zeros_like(y), sigma_abs=0.1, k=0.5, max_share=0.1)
    assert not rows.any() and "kept" in rec


@pytest.mark.parametrize("mode", ["reject", "huber"])
def test_fireflies_do_not_move_the_envmap(toy, mode):
    tr, grid, photo, bad, hot, sigma_abs = toy
    X_clean, _, _ = _solve(tr, grid, photo, sigma_abs, "keep")
    X_rob, info, rejected = _solve(tr, grid, bad, sigma_abs, mode)
    X_ls, _, _ = _solve(tr, grid, bad, sigma_abs, "keep")  # the broken variant: plain least squares
    assert set(hot) <= set(np.flatnonzero(rejected)) and rejected.sum() <= len(hot) + 2
    assert info["outliers"]["pixels"] == rejected.sum()
    err_rob, err_ls = _error(X_rob, X_clean), _error(X_ls, X_clean)
    assert err_rob < 0.05  # measured 0.00x (reject) / 0.0x (huber)
    assert err_ls > 0.3  # measured ~1: the fireflies' light becomes envmap


def test_no_outliers_same_answer_as_least_squares(toy):
    """Without outliers the robust solve's pause after OUTLIER_AFTER_STEPS and its continuation reproduce the
    uninterrupted solve (the continuation restarts from the same estimate, weights and edge scale)."""
    tr, grid, photo, _, _, sigma_abs = toy
    X_keep, info_keep, _ = _solve(tr, grid, photo, sigma_abs, "keep")
    X_rob, info, rejected = _solve(tr, grid, photo, sigma_abs, "reject")
    assert rejected is None and info["outliers"]["pixels"] == 0
    assert _error(X_rob, X_keep) < 1e-6


def test_the_verdict_counts_the_fitted_pixels_only(toy):
    tr, grid, photo, bad, hot, sigma_abs = toy
    X, _, rejected = _solve(tr, grid, bad, sigma_abs, "reject")
    env = tr.envmap_from_x(X)
    pred = tr.predict(X)
    y = bad.astype(np.float64)
    d = TargetData(tr, bad.reshape(SIDE, SIDE, 3), np.ones((SIDE, SIDE), bool), y, np.ones(len(y), bool))
    target = SimpleNamespace(noise_sigma=NOISE)
    v = assess(target, d, TargetSolution(env, None, pred, {}, rejected=rejected), lr_rel=1e-4)
    v_all = assess(target, d, TargetSolution(env, None, pred, {}), lr_rel=1e-4)
    assert v["chi2"] < 2.0 and v_all["chi2"] > 100  # the fireflies' residual is not the fit's
    assert v["pixels_rejected"] == pytest.approx(rejected.sum() / len(y))
    many = rejected.copy()
    many[: int(0.05 * len(y))] = True  # 5% dropped: the user is told
    v5 = assess(target, d, TargetSolution(env, None, pred, {}, rejected=many), lr_rel=1e-4)
    assert v5["grade"] != "green" and any("dropped as outliers" in r for r in v5["reasons"])


def test_the_chroma_run_follows_the_lead_on_its_own_thread(toy, monkeypatch):
    """The luminance run decides the outlier sets, the chroma run takes them when ready on the other thread
    (objcam.solvers.plan.known._robust_runs): the same envmap, bit for bit, as the runs one after the other."""
    from objcam.solvers.plan import known

    tr, grid, photo, bad, hot, sigma_abs = toy
    for mode in ("reject", "huber"):
        X_par, info_par, rej_par = _solve(tr, grid, bad, sigma_abs, mode)
        with monkeypatch.context() as m:
            m.setattr(known, "parallel_map", lambda fn, items, workers=None: [fn(i) for i in items])
            X_ser, info_ser, rej_ser = _solve(tr, grid, bad, sigma_abs, mode)
        assert "chroma" in info_par and info_par["outliers"] == info_ser["outliers"]
        assert np.array_equal(X_par, X_ser) and np.array_equal(rej_par, rej_ser)


def test_a_failing_lead_run_fails_the_others_instead_of_hanging(toy):
    import threading
    import time

    from objcam.solvers.plan.known import _robust_runs

    tr, grid, photo, _, _, sigma_abs = toy
    calls = []

    def one(w, steps, data, **kw):
        calls.append(w)
        if w == "lead":
            time.sleep(0.5)  # the chroma run is waiting for the lead's outlier set by then
            raise FloatingPointError("the lead's solve failed")
        return SimpleNamespace(x=np.zeros((tr.A.shape[2], 3)), steps=2)

    got = {}

    def run():
        try:
            _robust_runs(one, ["lead", "chroma"], tr, np.ones(len(photo), bool), photo, [[0, 1, 2]], sigma_abs,
                         SolveParams(), (None, None, None))
        except FloatingPointError as e:
            got["error"] = str(e)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(30)
    assert not t.is_alive() and got.get("error") == "the lead's solve failed", (got, calls)
    assert set(calls) == {"lead", "chroma"}, calls
