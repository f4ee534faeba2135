"""``objcam run`` from raw photos, every stage: the small synthetic photographed capture (tests/full_capture.py)
goes ingest -> sfm -> geometry -> texture -> probe -> scene -> transport -> solve -> evaluate -> analysis ->
report. With one photo and every albedo unknown its envmap is unconstrained, which the solve must say (no score is
asserted); without truth/ evaluate scores it against the chrome-ball probe instead; with the albedo given, the
envmap must beat bounds that broken answers to the same photos (tests/broken.py) miss. (The benchmark's version,
24 views at 800 x 600 against a known-geometry twin, is bench/e2e_bench.py.)"""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from objcam.envmap import from_file
from tests.full_capture import small_full_capture

# a coarse envmap and pooled pixels keep the run to about a minute on 2 cores
SETS = ["--set", "transport.env_height=8", "--set", "transport.downsample=2"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from objcam.pipeline.cli import main

    cap = small_full_capture(tmp_path_factory)
    work = tmp_path_factory.mktemp("full_run")
    assert main(["run", str(cap), "--work", str(work), "-q", *SETS]) == 0
    return cap, work


def test_every_stage_ran_and_the_unconstrained_envmap_is_flagged(run):
    """One photo and every albedo unknown: the albedo alone explains the photo, so the solve warns that the envmap
    comes from the priors, and no score of it is asserted. (Measured: envmap SSIM 0.339, what the truth's
    constant map scores (0.340); albedo relative RMSE 0.144, while the photo itself taken as the albedo scores
    0.087: neither number says anything about the solve.)"""
    cap, work = run
    for stage in ("ingest", "sfm", "geometry", "texture", "probe", "scene", "transport", "solve", "evaluate",
                  "analysis", "report"):
        assert (work / stage / "stage.json").is_file(), stage
    info = json.loads((work / "solve" / "t0" / "solve.json").read_text())
    assert info["envmap_constrained_by_data"] is False and info["albedo"] == "unknown"
    summary = json.loads((work / "solve" / "stage.json").read_text())["summary"]
    assert summary.startswith("WARNING: t0: one illumination and every albedo unknown"), summary
    m = json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]
    assert m["truth_source"] == "truth" and set(m["baselines"]) == {"constant", "row_mean"}
    assert (work / "report" / "index.html").stat().st_size > 10_000


def test_without_truth_evaluate_uses_the_chrome_ball(run, tmp_path):
    from objcam.pipeline.cli import main

    cap, work = run
    bare = tmp_path / "capture"
    shutil.copytree(cap, bare, copy_function=os.link, ignore=shutil.ignore_patterns("truth", "objcam"))
    w2 = tmp_path / "work"
    shutil.copytree(work, w2)  # the same artifacts: the stages' keys do not depend on truth/
    assert main(["run", str(bare), "--work", str(w2), "-q", "--until", "evaluate", *SETS]) == 0
    rec = json.loads((w2 / "solve" / "stage.json").read_text())
    assert rec["key"] == json.loads((work / "solve" / "stage.json").read_text())["key"]
    m = json.loads((w2 / "evaluate" / "metrics.json").read_text())["t0"]
    assert m["truth_source"] == "probe" and m["truth_file"].startswith("objcam/probe/")
    # scored with the baselines of the probe's map on the texels the ball shows; the envmap is the unconstrained
    # one above (its SSIM against the probe, 0.604, is what a constant map scores, 0.601), so no score is asserted
    assert set(m["baselines"]) == {"constant", "row_mean"} and "ssim_over_row_mean" in m["skill"]
    truth = json.loads((work / "evaluate" / "metrics.json").read_text())["t0"]
    assert m["baselines"]["constant"]["ssim"] != truth["baselines"]["constant"]["ssim"]  # another reference


STAGE_COMMANDS = ("geometry", "texture", "probe", "transport", "solve", "evaluate", "analysis", "report")


def test_each_stage_subcommand_reruns_its_stage_alone(run, tmp_path, capsys):
    """``objcam STAGE CAPTURE`` (the CLI's per-stage subcommands, make's targets): with the stage's artifacts
    removed from a copy of the run, the subcommand rebuilds that stage alone, under the same key and with the same
    artifact files, and finds every stage it needs cached."""
    from objcam.pipeline import graph
    from objcam.pipeline.cli import main

    cap, work = run
    w2 = tmp_path / "work"
    shutil.copytree(work, w2)
    for stage in STAGE_COMMANDS:
        before = json.loads((work / stage / "stage.json").read_text())
        shutil.rmtree(w2 / stage)
        capsys.readouterr()
        assert main([stage, str(cap), "--work", str(w2), "-q", *SETS]) == 0, stage
        out = capsys.readouterr().out
        assert f"{stage}: done in" in out, (stage, out)
        for up in graph.upstream_closure(stage):
            if up != stage and (work / up / "stage.json").is_file():
                assert f"{up}: skipped (unchanged)" in out, (stage, up, out)
        after = json.loads((w2 / stage / "stage.json").read_text())
        assert after["key"] == before["key"] and set(after["artifacts"]) == set(before["artifacts"]), stage
    assert json.loads((w2 / "evaluate" / "metrics.json").read_text())["t0"]["truth_source"] == "truth"


@pytest.fixture(scope="module")
def known(run, tmp_path_factory):
    """The same photos with the albedo given (bench/e2e_bench.py's derived capture), solved from the run's
    artifacts: (capture, work)."""
    from bench.e2e_bench import derived_capture
    from objcam.pipeline.cli import main

    cap, work = run
    root = tmp_path_factory.mktemp("known")
    known = derived_capture(cap, root / "known", albedo_known=True, probe=False)
    w2 = root / "work"
    shutil.copytree(work, w2)
    assert main(["run", str(known), "--work", str(w2), "-q", "--until", "evaluate", *SETS]) == 0
    return known, w2


# The known-albedo bounds, between the default's measured values and the broken answers' below
SSIM_MIN = 0.52  # measured 0.543 (0.562 at edge_tone 0.3; the truth's row-mean map 0.505)
SUN_DEG = 45.0  # two 22.5-degree texels; measured 21.8


def missed_bounds(m: dict) -> list[str]:
    """The known-albedo bounds an evaluate record ``m`` misses."""
    missed = [] if m["ssim"] > SSIM_MIN else ["ssim"]
    if not m["ssim"] > m["baselines"]["row_mean"]["ssim"]:
        missed.append("beats_row_mean")
    if not m["brightest_angle_deg"] < SUN_DEG:
        missed.append("sun")
    return missed


def test_photographed_targets_are_compared_up_to_the_camera_gain(known):
    """The target came from photos: its radiometry is relative (an unknown gain). With the albedo given, evaluate
    fits the one global scale (without it, the decoded values per second are ~17x the truth's radiance here and
    the comparison meaningless: make demo-full scored SSIM 0.12, relative RMSE 38 before)."""
    cap, w2 = known
    recs = json.loads((w2 / "scene" / "targets.json").read_text())
    assert [r["radiometry"] for r in recs] == ["relative"]
    m = json.loads((w2 / "evaluate" / "metrics.json").read_text())["t0"]
    assert "scale_channels" not in m and m["scale"] == pytest.approx(m["best_scale"])
    assert not 0.5 < m["scale"] < 2.0  # the camera's gain, which the fit took out
    assert json.loads((w2 / "solve" / "t0" / "solve.json").read_text())["albedo"] == "known"
    assert missed_bounds(m) == [], m


def test_report_tells_the_whole_capture(run, tmp_path):
    """The photographed capture's report in headless Chromium at 1280 px: a section per photo stage before the
    targets, the envmap beside the truth and the chrome ball with a working exposure slider, the parameters and
    the files; nothing wider than the page, no overlapping labels, no error; a screenshot of every section."""
    from tests.test_report_browser import layout, measure

    _, work = run
    page = work / "report" / "index.html"
    m = measure(page)
    assert not m["errors"], m["errors"]
    assert all(i["complete"] and i["w"] > 0 for i in m["images"])
    shots = tmp_path / "shots"
    info = layout(page, 1280, shots)
    ids = [s for s, _ in info["sections"]]
    want = ("ingest", "sfm", "geometry", "texture", "probe", "target-t0", "speed", "stages", "metrics", "params",
            "files")
    assert [s for s in ids if s in want] == list(want), ids
    assert info["scrollWidth"] <= 1280 and not info["wide"] and not info["clashes"], info
    # estimate, truth and chrome ball, drawn, and brighter at +2 EV
    assert len(info["before"]) == 3 and min(info["before"]) > 0, info["before"]
    assert all(a > b for a, b in zip(info["after"], info["before"])), (info["before"], info["after"])
    assert (info["output"], info["output_after"]) == ("0 EV", "+2 EV")
    text = page.read_text(encoding="utf-8")
    for needle in ("objcam 0", "Parameters used", "../solve/t0/envmap.exr", "Quality:", "camera positions"):
        assert needle in text, needle
    for sid in ids:
        assert (shots / f"{sid}.png").stat().st_size > 5_000, sid
    print(f"\nscreenshots of the report's sections: {shots}")


# The export of the photographed capture (below): bounds on its Mitsuba render against the solve's prediction
EXPORT_FULL_MAX = 0.01  # bias beyond Monte Carlo noise of the render with interreflections (issue 23's target); measured
# 0.76% with the bounce refit of the object's nodes (1.1% before it); the broken scale below 3.4%
EXPORT_DIRECT_MAX = 0.01  # bias beyond Monte Carlo noise of the direct-light render; measured 0.61%


def _render(mi, scene, h: int, w: int, f: int, seed: int = 0, spp: int = 256) -> np.ndarray:
    """(h, w, 3) float64: ``scene`` rendered, f x f blocks averaged (the transport's pooled pixels)."""
    img = np.asarray(mi.render(scene, seed=seed, spp=spp), np.float64)[..., :3]
    return img[: h * f, : w * f].reshape(h, f, w, f, 3).mean(axis=(1, 3))


def test_export_of_a_photographed_capture(run, tmp_path):
    """Unknown albedo, no pixel of known albedo: envmap and albedo are known only up to one scale, and the export
    bakes the solve's per-pixel albedo (objcam.export.bake) at the scale its A's interreflections assumed
    (objcam.export.scale: x 4.56 here, the envmap divided by it), so its Mitsuba scene renders the prediction:
    the direct light to 0.58% beyond Monte Carlo noise (bound 1%), with the interreflections to 0.73% (two 256-spp
    renders, their noise 0.63% taken out; bound 1%, issue 23's target). That needs the solve's A to reflect every
    surface at the albedo it writes: the bounce refit redoes the object's nodes too (its estimate 0.75 at this
    scale, where the texture stage's 0.65 was assumed; 1.1% before), and runs although this envmap is unconstrained.
    Broken: the solve's albedo baked at its own scale (before objcam.export.scale) renders the object 18% too dark
    and misses the bound (3.5%). Every SfM view travels with its camera."""
    import pycolmap

    from objcam.image_io import read_exr
    from objcam.pipeline.cli import main
    from objcam.scene import use_mitsuba
    from objcam.transport import load_transport
    from objcam.transport.gather import bounce_indirect

    cap, work = run
    out = tmp_path / "export"
    assert main(["export", str(cap), str(out), "--work", str(work)]) == 0
    rec = json.loads((out / "export.json").read_text())
    t0 = rec["targets"]["t0"]
    assert "envmap_scale" not in t0 and all("bake" in rec["meshes"][k] for k in rec["meshes"])
    k = t0["albedo_scale"]
    assert 2.0 < k < 10.0, t0  # the solve's albedo (~0.14 over the support) against the transport's guess (~0.62)
    env = read_exr(work / "solve" / "t0" / "envmap.exr")[..., :3]
    assert np.allclose(read_exr(out / "envmaps" / "t0.exr")[..., :3], env / np.float32(k), rtol=1e-6)
    pred = read_exr(work / "solve" / "t0" / "prediction.exr")[..., :3].astype(np.float64)
    h, w, f = pred.shape[0], pred.shape[1], t0["downsample"]
    used = np.any(pred != 0, axis=2)
    norm = np.linalg.norm(pred[used])
    mi = use_mitsuba()
    # with interreflections: one render
    scene = mi.load_file(str(out / "mitsuba" / "t0.xml"))
    fulls = [_render(mi, scene, h, w, f, seed=s) for s in (1, 2)]
    full_rel = np.linalg.norm((fulls[0] + fulls[1])[used] / 2 - pred[used]) / norm
    full_noise = np.linalg.norm(fulls[0][used] - fulls[1][used]) / 2 / norm
    full = float(np.sqrt(max(full_rel**2 - full_noise**2, 0.0)))
    # direct light against the model's direct part, rho A'_direct x (A' as the transport built it, less the gather's
    # indirect columns: the bounce refit changed only the indirect part of the solve's A')
    tr = load_transport(work / "transport", "t0")
    x = tr.x_from_envmap(from_file(env.astype(np.float64))).astype(np.float64)
    Ap = tr.rho_free()
    parts = tr.bounce_parts()
    ind = bounce_indirect(parts, np.ones(len(parts["node_rho"])))
    lit = np.zeros((h * w, 3))
    lit[tr.pixel_index] = np.stack([(Ap[c if Ap.shape[0] == 3 else 0] - ind) @ x[:, c] for c in range(3)], axis=1)
    albedo = read_exr(work / "solve" / "t0" / "albedo.exr")[..., :3].astype(np.float64)
    direct = lit.reshape(h, w, 3) * albedo
    two = mi.load_file(str(out / "mitsuba" / "t0.xml"), max_depth=2)
    halves = [_render(mi, two, h, w, f, seed=s) for s in (1, 2)]
    dnorm = np.linalg.norm(direct[used])
    rel = np.linalg.norm((halves[0] + halves[1])[used] / 2 - direct[used]) / dnorm
    noise = np.linalg.norm(halves[0][used] - halves[1][used]) / 2 / dnorm
    bias = float(np.sqrt(max(rel**2 - noise**2, 0.0)))
    # broken: the solve's albedo at its own scale (textures / k, envmap x k), what the export baked before
    params = mi.traverse(scene)
    for key in [key for key in params.keys() if key.endswith("reflectance.data") or key == "envmap.data"]:
        params[key] = params[key] * (k if key == "envmap.data" else 1.0 / k)
    params.update()
    broken = float(np.sqrt(max((np.linalg.norm(_render(mi, scene, h, w, f, seed=1)[used] - pred[used]) / norm) ** 2
                               - 2 * full_noise**2, 0.0)))  # one render: its noise is sqrt(2) x the two's mean
    print(f"export of the photographed capture: bias {full:.4f} (interreflections, noise {full_noise:.4f}; broken "
          f"scale {broken:.4f}),"
          f" direct light bias {bias:.4f} (noise {noise:.4f})")
    assert full < EXPORT_FULL_MAX and bias < EXPORT_DIRECT_MAX, (full, full_noise, bias, noise)
    assert broken > EXPORT_FULL_MAX, broken
    model = pycolmap.Reconstruction(str(out / "colmap"))
    views = sorted((work / "sfm" / "cameras" / "views").glob("*.json"))
    assert len(model.images) == len(views) + 1 and all((out / "images" / "views" / f"{v.stem}.png").is_file()
                                                       for v in views)


# (broken answer: measured SSIM, sun angle) -- each misses at least one bound
BROKEN = {
    "flat sky of the truth's mean": "SSIM 0.340, 78.8 deg",
    "estimate turned 90 degrees": "SSIM 0.203, 66.4 deg",
    "solve.ls=1e6": "SSIM 0.339, 78.7 deg",
}
# Not a broken answer here: one ray per pixel (the four transport sample counts at 1) scored SSIM 0.526 before
# session 14 and 0.730 after (interreflections modelled, the row below the horizon not solved): on this 8 x 16
# envmap over 2 x 2-pooled pixels the rays' noise averages out; tests/test_end_to_end.py keeps it as a broken
# answer on a finer grid, where it misses (relative RMSE 15-19 against 6.7).


@pytest.mark.parametrize("broken", list(BROKEN))
def test_a_broken_answer_fails_the_known_albedo_bounds(known, tmp_path, broken):
    """A test of the test (tests/broken.py): broken answers to the same photos miss the bounds above."""
    from objcam.baselines import with_baselines
    from objcam.envmap import resample_to_height
    from objcam.image_io import read_exr
    from objcam.metrics import best_scale, envmap_metrics
    from tests.broken import read_envmap, rerun, rotated, truth_constant

    cap, w2 = known
    if "." in broken.split(",")[0]:
        w = rerun(cap, w2, tmp_path / "work", SETS[1::2] + [s.strip() for s in broken.split(",")], until="evaluate")
        m = json.loads((w / "evaluate" / "metrics.json").read_text())["t0"]
    else:
        est, mask = read_envmap(w2)
        truth = resample_to_height(read_exr(cap / "truth" / "envmap.exr")[..., :3].astype(np.float64),
                                   est.shape[0])
        est = truth_constant(truth, mask) if broken.startswith("flat") else rotated(est, mask, 90.0)
        # evaluate's comparison for a photographed target: after the one best-fit scale
        m = with_baselines(envmap_metrics(est * best_scale(est, truth, mask), truth, mask), truth, mask)
    assert missed_bounds(m), (broken, m)
