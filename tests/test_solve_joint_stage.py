"""The solve stage with unknown albedo, through the real CLI: a tiny synthetic capture (48 x 48 px, 8 x 16 envmap,
two rotations of the sunrise HDRI, a 'dots' support whose albedo is not given), checked against truth/; then two
cameras stacked for one illumination; then bad input (conflicting illumination names, a diverging iteration that
keeps its last good estimate, a camera disagreeing with its image, illuminations without usable pixels)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from objcam.image_io import read_exr
from objcam.pipeline.cli import main
from objcam.solvers.plan.defaults import EDGE_LS_PER_SIGMA
from objcam.solvers.plan.rules import noise_lr

# solve.pinned_scale=false: this tiny capture (direct light only, 22.5-degree texels under a low sunrise sun) has a
# model error in the object's pixels that a scale pinned by their data alone passes on (measured: envmap relative
# RMSE 3.20 -> 3.69, SSIM 0.705 -> 0.689 on cam0_rot0), which would hide what these tests compare; the pinned scale
# is tested in tests/test_joint.py and tests/test_joint_family.py
RUN = ["--quiet", "--set", "transport.model=direct", "--set", "transport.env_height=8",
       "--set", "solve.pinned_scale=false"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    cap = tmp_path_factory.mktemp("joint") / "capture"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "64", "--rotations-deg", "[0, 150]",
                 "--support-albedo", "dots", "--support-albedo-known", "false", "--texture-scale", "0.03",
                 "--cameras", '[{"width": 48, "height": 48, "distance": 0.3}]']) == 0
    assert main(["run", str(cap), "--until", "evaluate", *RUN]) == 0
    return cap


def test_joint_outputs_and_scale_note(capture):
    for t in ("cam0_rot0", "cam0_rot150"):
        d = capture / "objcam" / "solve" / t
        for name in ("envmap.exr", "envmap_mask.png", "prediction.exr", "residual.exr", "target.exr",
                     "albedo.exr", "albedo.png", "albedo_mask.png", "solve.json"):
            assert (d / name).is_file(), name
        info = json.loads((d / "solve.json").read_text())
        # the object's albedo is given (0.6): its pixels are held at it and pin the scale
        assert info["albedo"] == "unknown" and not info["scale_ambiguous"] and "absolute" in info["note"]
        assert info["pixels_albedo_known"] > 20
        v = info["verdict"]  # so the verdict's line on an unknown object albedo stays out
        assert v["object_albedo_unknown"] < 0.5 and not any("object's albedo" in w for w in v["reasons"]), v
        assert info["illuminations_in_problem"] == 2 and info["cameras_in_problem"] == 1
        # solve.align: the true camera; this capture's model error (direct light, 8 rows) leans on the prediction's
        # gradients as a (-0.06, -0.06) px "shift" that removes no misfit: tried and not kept (fit gain ~0)
        al = info["alignment"]
        assert al["shift_px"] == [0.0, 0.0] and al["rounds"][-1]["taken"] is False, al
        alb = read_exr(d / "albedo.exr")
        assert alb.shape[:2] == (48, 48)
        assert alb.min() >= 0 and alb.max() <= 1.0 + 1e-6
    # the two targets share one camera, hence one albedo
    a0 = read_exr(capture / "objcam" / "solve" / "cam0_rot0" / "albedo.exr")
    a1 = read_exr(capture / "objcam" / "solve" / "cam0_rot150" / "albedo.exr")
    assert np.array_equal(a0, a1)
    stage = json.loads((capture / "objcam" / "solve" / "stage.json").read_text())
    assert "scale fixed by the pixels of known albedo" in stage["summary"]
    from objcam.transport import load_transport

    tr = load_transport(capture / "objcam" / "transport", "cam0_rot0")
    known = tr.pixel_index[~tr.unknown_albedo]
    flat = a0.reshape(-1, a0.shape[-1])[:, :3]
    np.testing.assert_allclose(flat[known], np.clip(tr.albedo[~tr.unknown_albedo], 1e-3, 1.0), rtol=1e-6)


def test_objective_monotone_and_kkt(capture):
    info = json.loads((capture / "objcam" / "solve" / "cam0_rot0" / "solve.json").read_text())
    h = np.array(info["objective_history"])
    assert h.size >= 2 and np.all(np.diff(h) <= 1e-12 * h[0])
    steps = np.array(info["objective_step_history"])
    assert np.all(np.diff(steps) <= 1e-12 * steps[0])  # every sub-step (x, rho, scale) is monotone
    assert info["kkt_residual_max"] < 1e-8  # the envmaps are exact for the final albedo
    assert info["kkt_residual_albedo_max"] < 0.05  # and the albedo near-stationary for them (tol 1e-4)


# Bounds of the two targets' albedo (after the fitted per-channel scale, evaluate's *_fitted_scale figures) and
# envmaps, between the measured values and the broken answers' (test_a_broken_answer_fails_the_joint_bounds).
# The albedo's: measured 0.097 / 0.916; the photo itself taken as
# the albedo scores 0.149 / 0.868 (cam0_rot0) and 0.218 / 0.830, its mean everywhere 0.202 / 0.291, one shadow
# ray and one camera ray per pixel (the four transport sample counts at 1) 0.171 / 0.756.
ALBEDO_RMSE_MAX, ALBEDO_SSIM_MIN = 0.13, 0.88
# The albedo as estimated (no fitted scale; the object's pixels pin it): SSIM measured 0.908 (0.895 in an earlier
# session); bounded at 0.85 before, which the photo taken as the albedo passed on cam0_rot0 (0.868; cam0_rot150
# 0.830; the albedo's mean everywhere 0.291)
ALBEDO_SSIM_AS_IS = 0.88
# The envmaps': the sun within half a 22.5-degree texel (measured 0 / 8.3 deg; 16 / 11 for the joint solve's own
# envmaps, solve.final_envmap=joint); SSIM measured 0.705 / 0.749 against the truth's row-mean map's 0.53 / 0.54
# (joint solve's own 0.36 / 0.71, solve.ls=1e6 0.34 / 0.37, one ray per pixel 0.47 / 0.82).
SUN_DEG, SSIM_MIN = 12.0, 0.65


def missed_bounds(r: dict) -> list[str]:
    """The bounds one target's evaluate record ``r`` misses."""
    checks = {"albedo_as_estimated": r["albedo_relative_rmse"] < 0.25 and r["albedo_ssim"] > ALBEDO_SSIM_AS_IS,
              "albedo_rmse": r["albedo_relative_rmse_fitted_scale"] < ALBEDO_RMSE_MAX,
              "albedo_ssim": r["albedo_ssim_fitted_scale"] > ALBEDO_SSIM_MIN, "sun": r["brightest_angle_deg"] < SUN_DEG,
              "ssim": r["ssim"] > SSIM_MIN,
              "beats_row_mean": r["ssim"] > r["baselines"]["row_mean"]["ssim"]}
    return [k for k, ok in checks.items() if not ok]


def test_albedo_and_envmap_against_truth(capture):
    m = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())
    for t in ("cam0_rot0", "cam0_rot150"):
        r = m[t]
        # the object's albedo pins the scale: evaluate scores the albedo as estimated (issue 29), measured 0.197 /
        # 0.895 (per channel 0.75 / 0.85 / 1.03 of the truth: a low sunrise sun in this tiny capture's 22.5-degree
        # texels, direct light only; 0.216 / 0.889 with solve.pinned_scale, 0.72 / 0.83 / 1.01; both hidden by
        # the fitted scale before); after the fitted per-channel scale, reported beside it: 0.097 / 0.916. A
        # constant albedo (the support's ground colour) scores 0.35 / 0.5 after that scale here
        assert r["albedo_scored_as"] == "as estimated" and r["albedo_scale"] == [1.0, 1.0, 1.0]
        assert r["albedo_relative_rmse"] < 0.25 and r["albedo_ssim"] > ALBEDO_SSIM_AS_IS, r
        assert r["albedo_relative_rmse_fitted_scale"] < 0.18 and r["albedo_ssim_fitted_scale"] > 0.85, r
        assert r["albedo_pixels"] > 1800
        # the object's known albedo pins the scale, so the envmap is compared as it is (no fitted scale)
        assert r["scale"] == 1.0 and "scale_channels" not in r
        assert missed_bounds(r) == [], (t, r)


BROKEN = ("flat sky of the truth's mean", "envmaps turned 90 degrees", "the photo as the albedo",
          "the albedo's mean everywhere", "solve.ls=1e6", "solve.final_envmap=joint",
          "transport.samples=1, transport.subpixel_samples=1, transport.object_samples=1, "
          "transport.object_subpixel_samples=1")


@pytest.mark.parametrize("broken", BROKEN)
def test_a_broken_answer_fails_the_joint_bounds(capture, tmp_path, broken):
    """A test of the test (tests/broken.py): each broken answer misses a bound above on at least one target."""
    import cv2

    from objcam.baselines import with_baselines
    from objcam.envmap import resample_to_height
    from objcam.metrics import albedo_metrics, envmap_metrics
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.stages.evaluate import truth_albedo_image, truth_envmap_path
    from objcam.transport import load_transport
    from tests.broken import read_envmap, rerun, rotated, truth_constant

    w = capture / "objcam"
    if "." in broken.split(",")[0]:
        w = rerun(capture, w, tmp_path / "work", RUN[2::2] + [s.strip() for s in broken.split(",")], "evaluate")
        m = json.loads((w / "evaluate" / "metrics.json").read_text())
    else:
        m = json.loads((w / "evaluate" / "metrics.json").read_text())
        scene = SceneArtifact.load(w / "scene")
        for t in m:
            est, mask = read_envmap(w, t)
            truth = resample_to_height(read_exr(truth_envmap_path(capture, t))[..., :3].astype(np.float64),
                                       est.shape[0])
            if broken.startswith("flat"):
                m[t] |= with_baselines(envmap_metrics(truth_constant(truth, mask), truth, mask), truth, mask)
            elif broken.startswith("envmaps turned"):
                m[t] |= with_baselines(envmap_metrics(rotated(est, mask, 90.0), truth, mask), truth, mask)
            else:
                d = w / "solve" / t
                amask = cv2.imread(str(d / "albedo_mask.png"), cv2.IMREAD_UNCHANGED) > 127
                alb = read_exr(d / "target.exr")[..., :3].astype(np.float64)
                if broken.startswith("the albedo's mean"):
                    alb = read_exr(d / "albedo.exr")[..., :3].astype(np.float64)
                    alb = np.where(amask[..., None], alb[amask].mean(axis=0), 0.0)
                true_alb = truth_albedo_image(capture, scene.folder, load_transport(w / "transport", t))
                m[t] |= albedo_metrics(alb, true_alb, amask)
    missed = {t: missed_bounds(r) for t, r in m.items()}
    assert any(missed.values()), (broken, m)
    if broken in ("the photo as the albedo", "the albedo's mean everywhere"):  # the as-estimated pair on each target
        assert all("albedo_as_estimated" in v for v in missed.values()), missed


def test_the_final_envmaps_ridge_follows_the_noise_unless_given(capture, tmp_path, monkeypatch):
    """The final step's known-albedo solve takes the noise's ridge at the targets' median (this capture's noise
    is above the rule's reference, so the rule's ridge is made smaller here by stubbing the noise rule's lr); a
    given solve.lr is used as given."""
    import objcam.solvers.plan.final as final

    real = final.noise_weights
    monkeypatch.setattr(final, "noise_weights", lambda *a, **k: (*real(*a, **k)[:1], 2.5e-5, real(*a, **k)[2]))
    for name, sets, want in (("rule", [], 2.5e-5), ("given", ["--set", "solve.lr=3e-4"], 3e-4)):
        work = tmp_path / name
        assert main(["run", str(capture), "--until", "solve", "--work", str(work), *RUN, *sets]) == 0
        for t in ("cam0_rot0", "cam0_rot150"):
            fin = json.loads((work / "solve" / t / "solve.json").read_text())["final_envmap"]
            assert fin["lr_relative"] == pytest.approx(want), (name, fin["lr_relative"])


def test_the_joint_solve_before_the_final_step_is_converged(capture, tmp_path):
    """The default stopping tolerance is where the envmaps have converged: a tenfold-or-more tighter one moves them
    by under 1% (relative L2). Measured on this capture against 1e-5: 3.9% / 7.5% at the former 1e-2, 1.4% / 1.5%
    at 1e-3, 0.2% / 0.2% at 1e-4 (the default); on the photographed sweep's twins the former early stop cost a
    median 0.05 SSIM (bench/results.md, session 51)."""
    work = tmp_path / "tight"
    assert main(["run", str(capture), "--until", "solve", "--work", str(work), *RUN, "--set", "solve.tol=1e-5"]) == 0
    for t in ("cam0_rot0", "cam0_rot150"):
        ours = read_exr(capture / "objcam" / "solve" / t / "envmap.exr")[..., :3]
        tight = read_exr(work / "solve" / t / "envmap.exr")[..., :3]
        assert np.linalg.norm(ours - tight) < 0.01 * np.linalg.norm(tight), t


def test_the_final_step_beats_the_joint_solves_own_envmaps_and_albedo(capture, tmp_path):
    """solve.final_envmap=known (the default) follows the joint solve with rounds of the albedo's TV step and every
    envmap solved again at that albedo by the known-albedo solver. Against the joint solve's own result
    (final_envmap=joint) both are closer to the truth on every target; without the TV step (albedo_tv=0) the
    albedo is the joint solve's and the envmaps still gain."""
    runs = {}
    # no_tv at the joint solve's own tolerance (a final step lets it stop at 1e-2): the same albedo as "joint"
    for name, sets in (("joint", ["solve.final_envmap=joint"]), ("no_tv", ["solve.albedo_tv=0", "solve.tol=1e-3"])):
        work = tmp_path / name
        args = ["run", str(capture), "--until", "evaluate", "--work", str(work), *RUN]
        assert main(args + [a for s in sets for a in ("--set", s)]) == 0
        runs[name] = json.loads((work / "evaluate" / "metrics.json").read_text())
        runs[name + "_solve"] = work / "solve"
    ours = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())
    joint, no_tv = runs["joint"], runs["no_tv"]
    for t in ("cam0_rot0", "cam0_rot150"):
        # measured: envmap SSIM 0.705 / 0.749 (0.681 / 0.751 without the TV step, 0.363 / 0.710 the joint
        # solve's own), relative RMSE 3.20 / 3.45 (3.65 / 3.68, 5.32 / 4.73); albedo relative RMSE 0.0966
        # against 0.0979 and SSIM 0.916 against 0.913 (this capture's dots are 2-4 pixels across; the bench's
        # dots scene: 0.0021 against 0.0031)
        assert ours[t]["ssim"] > joint[t]["ssim"] + 0.03, (ours[t], joint[t])
        assert ours[t]["relative_rmse"] < 0.9 * joint[t]["relative_rmse"], (ours[t], joint[t])
        assert no_tv[t]["relative_rmse"] < 0.9 * joint[t]["relative_rmse"], (no_tv[t], joint[t])
        assert no_tv[t]["albedo_relative_rmse"] == joint[t]["albedo_relative_rmse"]  # the joint solve's albedo
        # the TV step is about the albedo's structure: compared after the fitted scale (this capture's scale is
        # off by its 22.5-degree texels under a low sun, the same for both; see test_albedo_and_envmap_against_truth)
        assert ours[t]["albedo_relative_rmse_fitted_scale"] < joint[t]["albedo_relative_rmse_fitted_scale"]
        assert ours[t]["albedo_ssim_fitted_scale"] > joint[t]["albedo_ssim_fitted_scale"]
        assert ours[t]["relative_rmse"] < 0.95 * no_tv[t]["relative_rmse"], (ours[t], no_tv[t])
        info = json.loads((capture / "objcam" / "solve" / t / "solve.json").read_text())
        fin = info["final_envmap"]
        assert fin["prior"] == "edges" and fin["tone"] > 0 and fin["kkt_residual_max"] < 1e-8
        # the ridge follows the noise as for a known albedo, at the noise that set ls (1.5 sigma, the targets' median)
        assert fin["lr_relative"] == pytest.approx(noise_lr(fin["ls_relative"] / EDGE_LS_PER_SIGMA)), fin
        assert fin["rounds"] == 2 and min(fin["albedo_tv"]["edges"]) > 1000
        # the TV contrast chosen by GCV (objcam.solvers.albedo_gcv) from the ladder 0.006 x 4^k: the lowest score
        tv = fin["albedo_tv"]
        cands = tv["gcv"]["candidates"]
        assert tv["rule"] == "gcv" and tv["contrast"] == min(cands, key=lambda c: c["gcv"])["contrast"], tv
        assert json.loads((runs["joint_solve"] / t / "solve.json").read_text())["final_envmap"] is None
        assert json.loads((runs["no_tv_solve"] / t / "solve.json").read_text())["final_envmap"]["albedo_tv"] is None
    summary = json.loads((capture / "objcam" / "solve" / "stage.json").read_text())["summary"]
    assert "final step: 2 round(s) of the albedo's TV step" in summary


def _copy_capture(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("objcam"))
    return dst


def test_same_illumination_twice_in_one_camera_is_refused(capture, tmp_path, capsys):
    cap = _copy_capture(capture, tmp_path / "cap")
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('[[targets]]\n', '[[targets]]\nillumination = "sky"\n'))
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("objcam: error:") and "capture.toml" in line and "illumination" in line


def test_supersampled_transport_with_unknown_albedo_is_refused(capture, tmp_path, capsys):
    # the adaptive basis of objcam.solvers.refine is built for the known-albedo solve only: the transport stage
    # refuses before building A
    work = tmp_path / "work"
    assert main(["run", str(capture), "--until", "solve", "--work", str(work), *RUN,
                 "--set", "transport.supersample=2"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("objcam: error:") and "capture.toml" in line and "known albedo" in line
    assert "support's albedo unknown" in line and "transport.supersample=1" in line
    assert not (work / "transport" / "index.json").exists()


def test_diverging_iteration_keeps_the_last_good_estimate(capture, tmp_path):
    work = tmp_path / "work"
    # alpha > 2 makes the damped step overshoot: the guard stops it, the best estimate seen is written and marked
    assert main(["run", str(capture), "--until", "solve", "--work", str(work), *RUN,
                 "--set", "solve.method=paper", "--set", "solve.alpha=3.5"]) == 0
    stage = json.loads((work / "solve" / "stage.json").read_text())
    line = stage["summary"]
    assert "\n" not in line and line.startswith("WARNING") and "diverged" in line and "last good estimate" in line
    assert "fix:" in line
    for t in ("cam0_rot0", "cam0_rot150"):
        info = json.loads((work / "solve" / t / "solve.json").read_text())
        assert info["diverged"] and not info["converged"] and "last good estimate" in info["message"]
        h = np.array(info["objective_history"])
        # the estimate written is the best one seen, not the diverged last sweep
        assert info["objective"] and np.sum(info["objective"]) == pytest.approx(h.min(), rel=1e-9)
        assert h[-1] > 10 * h.min()
        env = read_exr(work / "solve" / t / "envmap.exr")
        assert np.isfinite(env).all() and env.max() > 0


def _edit_camera(path: Path, **kw) -> None:
    cam = json.loads(path.read_text())
    cam.update(kw)
    path.write_text(json.dumps(cam))


def _last_error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    return lines[-1] if lines else ""


def test_a_camera_disagreeing_with_its_image_size_is_refused(capture, tmp_path, capsys):
    cap = _copy_capture(capture, tmp_path / "cap")
    _edit_camera(cap / "targets" / "cam0_rot150.json", width=40)  # the second target's camera
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 2
    line = _last_error_line(capsys)
    assert line.startswith("objcam: error:") and "cam0_rot150.exr" in line and "48x48" in line and "40x48" in line
    assert not (cap / "objcam" / "solve").exists()


def _write_mask(path: Path, mask: np.ndarray) -> None:
    import cv2

    cv2.imwrite(str(path), (mask * 255).astype(np.uint8))


def _add_masks(cap: Path, masks: dict[str, np.ndarray]) -> None:
    toml = (cap / "capture.toml").read_text()
    for name, m in masks.items():
        _write_mask(cap / "targets" / f"{name}_mask.png", m)
        toml = toml.replace(f'camera = "targets/{name}.json"\n',
                            f'camera = "targets/{name}.json"\nmask = "targets/{name}_mask.png"\n')
    (cap / "capture.toml").write_text(toml)


def test_an_envmap_whose_pixels_are_all_invalid_is_refused(capture, tmp_path, capsys):
    cap = _copy_capture(capture, tmp_path / "cap")
    _add_masks(cap, {"cam0_rot150": np.zeros((48, 48))})
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 2
    line = _last_error_line(capsys)
    assert line.startswith("objcam: error:") and "cam0_rot150" in line and "no usable pixel" in line


def test_targets_of_one_camera_sharing_no_usable_pixel_are_refused(capture, tmp_path, capsys):
    # each target usable on one half of the image: no pixel constrains the shared albedo in both
    cap = _copy_capture(capture, tmp_path / "cap")
    left = np.zeros((48, 48))
    left[:, :24] = 1
    _add_masks(cap, {"cam0_rot0": left, "cam0_rot150": 1 - left})
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 2
    line = _last_error_line(capsys)
    assert line.startswith("objcam: error:") and "no pixel is usable in every target" in line and "fix:" in line


def test_one_illumination_with_every_albedo_unknown_is_flagged(tmp_path, capsys):
    """One target, object and support albedo both unknown: the albedo alone explains the photo, so the stage says
    the envmap is not constrained by the data (and a known object albedo lifts the warning)."""
    cap = tmp_path / "one"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "16", "--support-albedo", "dots",
                 "--support-albedo-known", "false", "--object-albedo-known", "false",
                 "--cameras", '[{"width": 32, "height": 32, "distance": 0.3}]']) == 0
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 0
    info = json.loads((cap / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert info["envmap_constrained_by_data"] is False
    summary = json.loads((cap / "objcam" / "solve" / "stage.json").read_text())["summary"]
    assert summary.startswith("WARNING: t0: one illumination and every albedo unknown") and "fix:" in summary
    toml = (cap / "capture.toml").read_text().replace("[[targets]]", "[albedo]\nobject = 0.6\n\n[[targets]]", 1)
    (cap / "capture.toml").write_text(toml)
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 0
    info = json.loads((cap / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert info["envmap_constrained_by_data"] is True
    # so does a one-colour object: one albedo over its varied normals leaves its shading to the envmap
    (cap / "capture.toml").write_text(toml.replace("object = 0.6", 'object = "uniform"'))
    assert main(["run", str(cap), "--until", "solve", *RUN]) == 0
    info = json.loads((cap / "objcam" / "solve" / "t0" / "solve.json").read_text())
    assert info["envmap_constrained_by_data"] is True and info["albedo_uniform"]["object"]
    # one illumination (lp > 0): the joint solve keeps its early stop before the final step, where two or more
    # converge (objcam.solvers.plan.defaults.JOINT_TOL_FINAL_ONE_ILLUMINATION, session 51)
    assert info["final_envmap"] and info["message"].endswith("(relative decrease < 0.01)"), info["message"]


def _declare_object(capture: Path, dest: Path, decl: str | None) -> Path:
    """A copy of ``capture`` (its inputs) whose object albedo is ``decl`` (a capture.toml value) or unknown."""
    shutil.copytree(capture, dest, ignore=shutil.ignore_patterns("objcam"))
    toml = dest / "capture.toml"
    text = toml.read_text()
    assert "\nobject = 0.6\n" in text
    toml.write_text(text.replace("\nobject = 0.6\n", f"\nobject = {decl}\n" if decl else "\n", 1))
    return dest


def test_a_one_colour_object_is_solved_for_one_albedo(capture, tmp_path):
    """capture.toml's ``object = "uniform"``: the object's pixels share one albedo per colour, estimated (not given),
    which keeps the object's shading across its surface as data where a free albedo per pixel absorbs it (session
    50). Measured on this capture (8 x 16, direct light, the scale fitted): envmap SSIM 0.917 / 0.891 against
    0.729 / 0.884 with an albedo per pixel (the object's albedo given: 0.894 / 0.869), the albedo's relative RMSE
    0.100 against 0.138."""
    out = {}
    for name, decl in (("pixel", None), ("uniform", '"uniform"')):
        cap = _declare_object(capture, tmp_path / name, decl)
        assert main(["run", str(cap), "--until", "evaluate", *RUN, "--set", "evaluate.scale_invariant=true"]) == 0
        out[name] = json.loads((cap / "objcam" / "evaluate" / "metrics.json").read_text())
        info = json.loads((cap / "objcam" / "solve" / "cam0_rot0" / "solve.json").read_text())
        scene = json.loads((cap / "objcam" / "scene" / "stage.json").read_text())
        if name == "uniform":
            assert scene["metrics"]["uniform_albedo"] == ["object"] and "object (one colour)" in scene["summary"]
            from objcam.transport import load_transport

            tr = load_transport(cap / "objcam" / "transport", "cam0_rot0")
            alb = read_exr(cap / "objcam" / "solve" / "cam0_rot0" / "albedo.exr")[..., :3].reshape(-1, 3)
            on = tr.pixel_index[(tr.object_fraction >= 1) & tr.unknown_albedo]
            assert on.size == info["pixels_albedo_uniform"] > 20
            assert np.ptp(alb[on], axis=0).max() == 0.0  # one value per colour
            np.testing.assert_allclose(alb[on[0]], info["albedo_uniform"]["object"], atol=1e-5)
            assert info["scale_ambiguous"] and info["envmap_constrained_by_data"]
            assert info["verdict"]["object_albedo_unknown"] == 0.0  # one value: the low sky's warning stays out
            assert main(["run", str(cap), *RUN, "--set", "evaluate.scale_invariant=true"]) == 0  # + the report
            html = (cap / "objcam" / "report" / "index.html").read_text()
            assert "One colour each, as capture.toml declares" in html and "object (" in html
        else:
            assert info["albedo_uniform"] is None and info["verdict"]["object_albedo_unknown"] == 1.0
    uni, pix = out["uniform"]["cam0_rot0"], out["pixel"]["cam0_rot0"]
    assert uni["ssim"] > pix["ssim"] + 0.1 and uni["relative_rmse"] < 0.5 * pix["relative_rmse"], (uni, pix)
    assert uni["albedo_relative_rmse_fitted_scale"] < 0.85 * pix["albedo_relative_rmse_fitted_scale"]


def test_the_support_level_of_the_bounce_is_chosen_by_the_joint_objective(capture, tmp_path):
    """No pixel of known albedo, a one-colour object and the gathered interreflections: the support's mean albedo
    the refitted bounce uses is the level (of BOUNCE_LEVELS, refined by a parabola) whose solve has the lowest
    objective; with an albedo per object pixel (solve.bounce_level=auto) the transport's guess stays."""
    from objcam.solvers.plan.defaults import BOUNCE_LEVELS

    sets = ["--set", "transport.model=auto", "--set", "transport.auto_noise=1e-6", "--set", "transport.env_height=8"]
    cap = _declare_object(capture, tmp_path / "uniform", '"uniform"')
    assert main(["run", str(cap), "--until", "solve", "--quiet", *sets]) == 0
    refit = json.loads((cap / "objcam" / "solve" / "cam0_rot0" / "solve.json").read_text())["bounce_refits"][0]
    search = refit["level_search"]
    tried = {float(k): v for k, v in search["levels"].items()}
    assert len(tried) >= 3 and set(tried) <= set(BOUNCE_LEVELS)
    best = min(tried, key=tried.get)
    i = BOUNCE_LEVELS.index(best)  # the lowest has its neighbours tried, and the choice lies between them
    assert all(BOUNCE_LEVELS[j] in tried for j in (i - 1, i + 1) if 0 <= j < len(BOUNCE_LEVELS))
    assert BOUNCE_LEVELS[max(i - 1, 0)] <= search["chosen"] <= BOUNCE_LEVELS[min(i + 1, len(BOUNCE_LEVELS) - 1)]
    assert "the level the joint objective chose" in refit["albedo_scale_from"]
    cap = _declare_object(capture, tmp_path / "pixel", None)
    assert main(["run", str(cap), "--until", "solve", "--quiet", *sets]) == 0
    refit = json.loads((cap / "objcam" / "solve" / "cam0_rot0" / "solve.json").read_text())["bounce_refits"][0]
    assert "level_search" not in refit and "transport's guess" in refit["albedo_scale_from"]


def test_silhouette_pixels_are_left_out_of_the_joint_fit(capture, tmp_path):
    """Pixels mixing the object (known albedo) and the support (unknown) cannot be fitted with one albedo: the
    exact joint solve leaves them out (and says how many); ``solve.mixed_pixels=fit`` keeps them."""
    from objcam.transport import load_transport

    tr = load_transport(capture / "objcam" / "transport", "cam0_rot0")
    mixed = (tr.object_fraction > 0) & (tr.object_fraction < 1) & tr.unknown_albedo
    assert mixed.sum() > 5  # the bunny's silhouette
    info = json.loads((capture / "objcam" / "solve" / "cam0_rot0" / "solve.json").read_text())
    assert info["pixels_excluded_mixed"] == int(mixed.sum())
    stage = json.loads((capture / "objcam" / "solve" / "stage.json").read_text())
    assert f"{int(mixed.sum())} silhouette pixels left out" in stage["summary"]
    mask = read_exr(capture / "objcam" / "solve" / "cam0_rot0" / "prediction.exr")[..., :3].reshape(-1, 3)
    assert np.all(mask[tr.pixel_index[mixed]] == 0)  # not fitted, not predicted
    work = tmp_path / "fit"
    assert main(["run", str(capture), "--until", "evaluate", "--work", str(work), *RUN,
                 "--set", "solve.mixed_pixels=fit"]) == 0
    kept = json.loads((work / "solve" / "cam0_rot0" / "solve.json").read_text())
    assert kept["pixels_excluded_mixed"] == 0 and kept["pixels_used"] == info["pixels_used"] + int(mixed.sum())
    ours = json.loads((capture / "objcam" / "evaluate" / "metrics.json").read_text())
    fit = json.loads((work / "evaluate" / "metrics.json").read_text())
    # measured with the joint solve converged (relative decrease 1e-4, session 51): albedo relative RMSE after the
    # fitted scale 0.092 left out against 0.108 fitted (the fitted silhouette pixels get albedos that absorb the
    # misfit); envmap relative RMSE 0.659 / 2.328 against 0.641 / 2.373, SSIM 0.895 / 0.887 against 0.899 / 0.878
    for t in ("cam0_rot0", "cam0_rot150"):
        assert ours[t]["albedo_relative_rmse_fitted_scale"] < 0.9 * fit[t]["albedo_relative_rmse_fitted_scale"]
    mean = lambda m, k: np.mean([m[t][k] for t in ("cam0_rot0", "cam0_rot150")])  # noqa: E731
    assert mean(ours, "relative_rmse") < mean(fit, "relative_rmse"), (ours, fit)
    assert mean(ours, "ssim") > mean(fit, "ssim") - 3e-3


def test_bounce_refit_redoes_the_support_light_from_the_transport_as_built(capture, tmp_path):
    """With the gathered interreflections (transport.model=auto) the solve redoes the support's light from its
    albedo estimate; a refit always starts from A' as built, so refitting twice from one estimate gives the A' of
    refitting once (a refit on top of a refit would count the change twice)."""
    from types import SimpleNamespace

    from objcam.solvers.plan.bounce import refit_bounce
    from objcam.solvers.plan.params import SolveParams as Params
    from objcam.transport import load_transport

    work = tmp_path / "auto"
    # auto_noise: a target noise this low makes model=auto add the (gathered) interreflections
    assert main(["run", str(capture), "--until", "solve", "--work", str(work), "--quiet",
                 "--set", "transport.model=auto", "--set", "transport.auto_noise=1e-6",
                 "--set", "transport.env_height=8"]) == 0
    info = json.loads((work / "solve" / "cam0_rot0" / "solve.json").read_text())
    assert len(info["bounce_refits"]) == 1 and info["bounce_refits"][0]["cells_updated"] > 0
    # the support's cells no pixel sees take the seen cells' mean estimate (issue 29), recorded
    refit = info["bounce_refits"][0]
    assert refit["cells_unseen_filled"] > 0 and 0 < refit["unseen_cell_albedo"] <= 1
    # the solve before the refit only provides its albedo: loose, quadratic prior; the final one is the edge prior's
    first = info["bounce_refits"][0]["first_solve"]
    assert first["prior"] == "smooth" and first["tol"] == 3e-2 and info["prior"] == "edges"
    # ... on one pixel in 2 x 2 (two illuminations: every pixel's albedo follows from its least squares)
    assert first["pixel_stride"] == 2 and 0.2 * info["pixels_used"] < first["pixels"] < 0.4 * info["pixels_used"]
    assert info["converged"] and info["kkt_residual_max"] < 1e-8
    assert "support light redone 1x" in json.loads((work / "solve" / "stage.json").read_text())["summary"]
    tr = load_transport(work / "transport", "cam0_rot0")
    assert tr.bounce_parts() is not None
    from objcam.solvers.assemble import grey_rho_free

    rows = np.flatnonzero(~((tr.object_fraction > 0) & (tr.object_fraction < 1) & tr.unknown_albedo))
    A = grey_rho_free(tr, rows, tr.texel_index)
    alb = read_exr(work / "solve" / "cam0_rot0" / "albedo.exr")[..., :3].reshape(-1, 3)[tr.pixel_index[rows]]
    rho = np.where(tr.unknown_albedo[rows, None], alb, np.clip(tr.albedo[rows], 1e-3, 1.0))
    cam = dict(tr=tr, rows=rows, A=A.copy())
    res = SimpleNamespace(rho=[rho], diverged=False, objective=np.ones(3))
    comp = SimpleNamespace(texel_index=tr.texel_index)
    once = refit_bounce([cam], comp, res, Params())
    A1 = cam["A"].copy()
    refit_bounce([cam], comp, res, Params())
    assert once and not np.array_equal(A1, A)  # the refit changed A'
    np.testing.assert_array_equal(cam["A"], A1)  # and a second one from the same estimate leaves it there


def test_a_refit_that_finds_nothing_to_redo_still_converges_to_the_requested_tolerance(capture, tmp_path,
                                                                                        monkeypatch):
    """The first solve stops early (relative decrease 3e-2) when a bounce refit will follow; if the refit then has
    no cell to redo, the solve is finished at the requested tolerance, not left at the early stop."""
    import objcam.solvers.plan.bounce as bounce
    from objcam.solvers.plan.defaults import JOINT_TOL_FINAL

    monkeypatch.setattr(bounce, "refit_bounce", lambda *a, **k: [])
    work = tmp_path / "auto"
    assert main(["run", str(capture), "--until", "solve", "--work", str(work), "--quiet",
                 "--set", "transport.model=auto", "--set", "transport.auto_noise=1e-6",
                 "--set", "transport.env_height=8"]) == 0
    info = json.loads((work / "solve" / "cam0_rot0" / "solve.json").read_text())
    assert info["bounce_refits"] == [] and info["converged"]
    assert f"< {JOINT_TOL_FINAL:g}" in info["message"], info["message"]  # the final step follows


def test_two_cameras_one_illumination_with_the_bounce_refit(tmp_path):
    """Two cameras see one illumination (stacked into one system, an albedo each) with the gathered
    interreflections: the refit redoes each camera's A' and the solve still recovers the albedo."""
    cap = tmp_path / "two"
    assert main(["synth", str(cap), "--envmap", "sunrise", "--spp", "32", "--support-albedo", "dots",
                 "--support-albedo-known", "false", "--texture-scale", "0.03",
                 "--cameras", '[{"width": 40, "height": 40, "distance": 0.3}, '
                              '{"width": 40, "height": 40, "distance": 0.3, "azimuth_deg": 30}]']) == 0
    toml = cap / "capture.toml"  # one illumination seen by both cameras
    toml.write_text(toml.read_text().replace('[[targets]]\n', '[[targets]]\nillumination = "sky"\n'))
    assert main(["run", str(cap), "--until", "evaluate", "--quiet", "--set", "transport.model=auto",
                 "--set", "transport.auto_noise=1e-6", "--set", "transport.env_height=8"]) == 0
    names = json.loads((cap / "objcam" / "solve" / "stage.json").read_text())["metrics"]["targets"]
    assert len(names) == 2
    for t, info in names.items():
        assert info["cameras_in_problem"] == 2 and info["illuminations_in_problem"] == 1
        assert {r["camera"] for r in info["bounce_refits"]} == {0, 1}
        assert info["pixels_excluded_mixed"] > 0 and info["kkt_residual_max"] < 1e-8
    m = json.loads((cap / "objcam" / "evaluate" / "metrics.json").read_text())
    for t, r in m.items():
        # measured after the fitted scale: albedo 0.129 / 0.139 relative RMSE, SSIM 0.83 / 0.84; as estimated
        # (the pinned scale, what evaluate now reports first) 0.327 / 0.326: per channel 0.60 / 0.71 / 0.84 of the
        # truth (0.63 / 0.73 / 0.86 before the pinned scale), the one sunrise's low sun in 22.5-degree texels;
        # envmap SSIM 0.68, sun 0 degrees off (the joint solve's own envmap, solve.final_envmap=joint: 0.38, 9.3)
        assert r["albedo_ssim_fitted_scale"] > 0.75, (t, r)
        assert r["albedo_relative_rmse"] < 0.4 and r["albedo_scored_as"] == "as estimated", (t, r)
        # the photo itself taken as the albedo scores 0.162 / 0.823 and 0.163 / 0.832: the albedo's SSIM does not
        # tell them apart, its relative RMSE does, by a thin margin (one illumination: the albedo is constrained
        # only through the envmap that the two views share)
        assert r["albedo_relative_rmse_fitted_scale"] < ALBEDO_RMSE_TWO_CAMERAS, (t, r)
        assert r["ssim"] > 0.6 and r["scale"] == 1.0 and r["brightest_angle_deg"] < 5.0, (t, r)
    # a test of the test (tests/broken.py): the truth's flat sky and the envmap turned 90 degrees miss the envmap
    # bounds, the photo taken as the albedo misses the albedo's
    _broken_answers_miss(cap, cap / "objcam", m, lambda r: r["ssim"] > 0.6 and r["brightest_angle_deg"] < 5.0,
                         lambda r: r["albedo_relative_rmse_fitted_scale"] < ALBEDO_RMSE_TWO_CAMERAS
                         and r["albedo_ssim_fitted_scale"] > 0.75)


ALBEDO_RMSE_TWO_CAMERAS = 0.15  # measured 0.129 / 0.139; the photo as the albedo 0.162 / 0.163 (was 0.2: passed)


def _broken_answers_miss(capture, work, metrics, env_ok, albedo_ok) -> None:
    """Score the broken answers of every target of ``metrics`` as evaluate does (known scale) and assert each
    fails ``env_ok`` / ``albedo_ok`` (predicates on a metrics dict) on at least one target."""
    import cv2

    from objcam.envmap import resample_to_height
    from objcam.metrics import albedo_metrics, envmap_metrics
    from objcam.schemas.artifacts import SceneArtifact
    from objcam.stages.evaluate import truth_albedo_image, truth_envmap_path
    from objcam.transport import load_transport
    from tests.broken import read_envmap, rotated, truth_constant

    scene = SceneArtifact.load(work / "scene")
    flat, turned, photo = [], [], []
    for t in metrics:
        est, mask = read_envmap(work, t)
        truth = resample_to_height(read_exr(truth_envmap_path(capture, t))[..., :3].astype(np.float64), est.shape[0])
        flat.append(env_ok(envmap_metrics(truth_constant(truth, mask), truth, mask)))
        turned.append(env_ok(envmap_metrics(rotated(est, mask, 90.0), truth, mask)))
        d = work / "solve" / t
        amask = cv2.imread(str(d / "albedo_mask.png"), cv2.IMREAD_UNCHANGED) > 127
        true_alb = truth_albedo_image(capture, scene.folder, load_transport(work / "transport", t))
        photo.append(albedo_ok(albedo_metrics(read_exr(d / "target.exr")[..., :3].astype(np.float64), true_alb,
                                              amask)))
    assert not all(flat) and not all(turned) and not all(photo), (flat, turned, photo)


def test_the_subsampled_first_solve_gives_every_pixel_the_albedo_of_its_least_squares():
    """The solve before a bounce refit fits one pixel in 2 x 2 (and every pixel of known albedo); the others get
    the per-pixel least-squares albedo at its envmaps. On noise-free data y = rho A' x the pixels it did not fit
    come out at their true albedo, and the held pixels at theirs."""
    from types import SimpleNamespace

    from objcam.envmap import EnvGrid
    from objcam.solvers.jointauto import JointSetup
    from objcam.solvers.plan.bounce import solve_subsampled, subsample

    rng = np.random.default_rng(3)
    h, w, n, L = 20, 20, 24, 3
    pix = np.arange(h * w)
    A = rng.uniform(0.0, 1.0, (pix.size, n)) * (rng.uniform(size=(pix.size, n)) < 0.6)
    x = rng.uniform(0.2, 1.0, (n, L, 3))
    rho = rng.uniform(0.2, 0.9, (pix.size, 3))
    fixed = rng.uniform(size=pix.size) < 0.1
    Y = rho[:, None, :] * np.einsum("mn,nlc->mlc", A, x)
    rho0 = np.where(fixed[:, None], rho, 0.5)
    cam = dict(tr=SimpleNamespace(pixel_index=pix, image_shape=(h, w)), rows=pix, A=A.astype(np.float32), Y=Y,
               rho0=rho0, fixed=fixed)
    grid = EnvGrid(4)
    setup = JointSetup(prior="smooth", ls=1e-9, lr=1e-12, rule="off", tol=1e-12, max_iter=300, polish=False)
    res, _, fitted = solve_subsampled([cam], subsample([cam], 2), grid, np.arange(n), setup, None)
    on_grid = ((pix // w) % 2 == 0) & ((pix % w) % 2 == 0)
    assert fitted == int((on_grid | fixed).sum())
    est = res.rho[0]
    assert est.shape == rho.shape
    np.testing.assert_array_equal(est[fixed], rho[fixed])
    off = ~(on_grid | fixed)
    assert off.sum() > 200
    np.testing.assert_allclose(est[off], rho[off], rtol=1e-5)  # measured 2e-7


def test_the_final_envmaps_stack_the_cameras_at_their_albedo():
    """The final envmap solve (objcam.solvers.plan.final.final_envmaps) of y_lc = diag(rho_pc) A'_p x_lc over two
    cameras: the same minimiser as the known-albedo edge solver given the float64 stacked Gram matrices, and, with
    noise-free data and a faint prior, the true envmaps."""
    from objcam import solvers
    from objcam.envmap import EnvGrid
    from objcam.solvers.basis import texel_basis
    from objcam.solvers.edges import solve_edges
    from objcam.solvers.plan.defaults import EDGE_EPS_KNOWN
    from objcam.solvers.plan.final import final_envmaps
    from objcam.solvers.plan.params import SolveParams as Params

    rng = np.random.default_rng(3)
    grid = EnvGrid(4)
    texel_index = np.arange(grid.n_texels // 2)  # the upper hemisphere, 16 texels
    n, L = texel_index.size, 2
    X_true = rng.uniform(0.1, 2.0, (n, L, 3))
    cams, rhos = [], []
    for m in (60, 45):
        A = rng.random((m, n)).astype(np.float32)
        rho = rng.uniform(0.2, 1.0, (m, 3))
        Y = rho[:, None, :] * np.einsum("mn,nlc->mlc", A.astype(np.float64), X_true)
        cams.append(dict(A=A, Y=Y))
        rhos.append(rho)
    params = Params()
    X, info = final_envmaps(cams, rhos, grid, texel_index, params, ls=1e-3)
    assert X.shape == (n, L, 3) and info["ls_relative"] == 1e-3 and info["kkt_residual_max"] < 1e-8
    # reference: the stacked system in float64, solved by the known-albedo edge solver
    grams = [sum((r[:, c, None] * cam["A"]).T @ (r[:, c, None] * cam["A"]) for cam, r in zip(cams, rhos))
             for c in range(3)]
    D = solvers.difference_operator(grid, texel_index)
    ls_abs, lr_abs = solvers.absolute_weights(sum(grams) / 3, 1e-3, params.ridge)
    P = texel_basis(grid, texel_index, 1.0)
    for l in range(L):
        rhs = [sum((r[:, c, None] * cam["A"]).T @ cam["Y"][:, l, c:c + 1] for cam, r in zip(cams, rhos))
               for c in range(3)]
        yy = np.array([sum(float(cam["Y"][:, l, c] @ cam["Y"][:, l, c]) for cam in cams) for c in range(3)])
        ref = solve_edges(grams, rhs, [[0], [1], [2]], yy, D, ls_abs, lr_abs, steps=params.edge_steps,
                          eps_rel=EDGE_EPS_KNOWN, tone=params.edge_tone, tone_floor=params.edge_tone_floor, basis=P)
        np.testing.assert_allclose(X[:, l], ref.x, rtol=1e-4, atol=1e-6)
    # a faint prior on the texels themselves: the noise-free data give back the truth
    X0, _ = final_envmaps(cams, rhos, grid, texel_index, Params(lr=1e-12, texel_group=0), ls=1e-9)
    np.testing.assert_allclose(X0, X_true, rtol=1e-3)


def test_several_illuminations_each_on_its_own_camera_are_told_to_share_one():
    """Two targets with every albedo unknown, each alone on its camera (SfM posed them apart, or two camera files):
    the warning's fix is one camera position, not 'photograph two or more illuminations' (which they did)."""
    from objcam.solvers.plan.summary import solve_summary

    info = {"kkt_residual_max": 1e-15, "albedo": "unknown", "envmap_constrained_by_data": False,
            "relative_image_residual": 0.0, "illuminations_in_problem": 1}
    one, _ = solve_summary({"t0": info | {"illumination": "t0"}}, "exact", 1.0)
    two, _ = solve_summary({"rot0": info | {"illumination": "rot0"}, "rot150": info | {"illumination": "rot150"}},
                           "exact", 1.0)
    assert "photograph two or more illuminations" in one and "camera position" not in one
    assert two.startswith("WARNING: rot0, rot150: one illumination") and "one camera position" in two
    assert "photograph two or more illuminations" not in two
    # one illumination seen by two cameras: still one illumination
    views, _ = solve_summary({"a": info | {"illumination": "sun"}, "b": info | {"illumination": "sun"}}, "exact", 1.0)
    assert "photograph two or more illuminations" in views
