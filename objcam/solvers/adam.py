"""``method=adam``: the method's baseline, gradient descent with Adam through Mitsuba 3's differentiable renderer.

It exists to be beaten, and to be fair to, so it minimises OUR objective over the same unknowns:

    F = sum_l ||rho * A' x_l - y_l||^2 + ls s ||D x_l||^2 + lr s ||x_l||^2  (+ lp t ||G rho||^2)

per target l of one camera (pooled pixels at the transport's kept rows that are usable; rho per pixel and channel,
shared by the camera's targets, estimated where the albedo is unknown and fixed at the known albedo elsewhere;
the renderer stands in for A' x: its scene holds the known albedos and renders the unknown ones at 1, so the
rendered model is ``render(x_l)`` where the albedo is known and ``rho * render(x_l)`` where it is estimated -- an
earlier version multiplied known pixels by their albedo a second time, which fitted x to 1 / rho of the truth;
``s`` the data scale mean(diag(A^T A)), A = diag(rho0) A' at the initial albedo, so the relative weights mean what they mean for the exact
solve). Parameterisation: x = exp(theta) per kept texel and channel (positive, scale-free steps for radiances
spanning 4 decades), rho = sigmoid(phi) (inside (0, 1)). Initialisation: a constant sky matching the photo's mean
and rho = 0.5. ``render`` is ``mi.render`` with Mitsuba's ``prb`` integrator (path replay backpropagation; global
illumination up to ``max_depth``), a perspective sensor equal to the target camera (centred principal point,
square pixels: OpenCV axes turned to Mitsuba's by a half turn about z) and the envmap emitter's bitmap built from
x exactly as the synthetic targets' (objcam.render.mitsuba_box_bitmap, columns reversed, Mitsuba's wrap
columns); the gradient with respect to that bitmap (dr.grad) is pulled back to the texels by the transpose of
this linear map. Stochastic gradients (``spp`` per pixel, a new seed each iteration); Adam (Kingma & Ba) with
the given learning rate; it stops at ``max_iter``, at the time budget ``seconds`` (early stopping) or when the
objective stops improving: every ``window`` iterations the objective at the current estimate, evaluated with the
transport matrix (noise-free: the rendered loss of a 4-spp image is dominated by the render's own variance once
the fit is close, and plateaus there while x still moves; recorded with the start and the end in
``objective_history_transport``) is compared with the best so far; after ``patience`` windows without a relative improvement of ``converge_tol`` the learning rate is
halved (reduce-on-plateau, down to lr / 16; the stochastic gradients of a few-spp render otherwise leave Adam
rattling at the noise level its step size sets), and when the smallest rate also stalls it stops ("converged"). The
loss history and the iterations are in the result.
Illumination groups across cameras are not stacked here (each target has its own envmap).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from objcam.dr_memory import padded
from objcam.errors import StageError


@dataclass
class AdamSettings:
    lr: float = 0.05
    seconds: float = 60.0
    max_iter: int = 2000
    spp: int = 4
    ls: float = 0.1
    lr_ridge: float = 1e-4
    lp: float = 0.0
    max_depth: int = 3
    upsample: int = 2
    converge_tol: float = 1e-3
    window: int = 25
    patience: int = 2
    seed: int = 0
    #: False: where the plateau rule would stop ("converged"), record the time and go on at the smallest rate
    #: until the time budget or max_iter (to see whether Adam, given more time, ever reaches the solution)
    stop_on_plateau: bool = True


@dataclass
class AdamTargetResult:
    envmap: np.ndarray  # (H, 2H, 3)
    prediction: np.ndarray  # (H', W', 3) pooled rho * A' x
    albedo: np.ndarray | None  # (H', W', 3) or None (known albedo)
    albedo_mask: np.ndarray | None
    info: dict = field(default_factory=dict)


@dataclass
class AdamProblem:
    """The unknowns and the objective F (module docstring) of one camera's targets, as Adam sees them.

    ``objective`` evaluates F with the transport matrix A' in place of the renderer (noise-free), so it also
    scores any other solver's (x, rho) on the very function Adam minimises (bench/ablation.py does, to say how far
    Adam's plateau is from the optimum).
    """

    tr: object  # objcam.transport.storage.Transport of the camera
    pix: np.ndarray  # (M,) flat pooled-image indices of the usable pixels (all targets valid)
    Y: np.ndarray  # (L, M, 3) the targets' pixels
    unknown: np.ndarray  # (M,) bool: albedo estimated
    rho_known: np.ndarray  # (M, 3) the albedo where it is known (clipped into [1e-3, 1])
    rho0: np.ndarray  # (M, 3) initial albedo: 0.5 where unknown
    Ap: np.ndarray  # (M, N) float64 rho-free transport (grey; the channel mean of an RGB one)
    DtD: object  # (N, N) sparse envmap smoothness D^T D
    ls: float  # absolute weights: relative ones x s_data = mean(diag(A^T A)), A = diag(rho0) A'
    lrr: float
    lp: float  # relative albedo weight (x t_data)
    G: object | None  # albedo smoothness operator, when lp > 0 and some albedo is unknown
    t_data: float  # mean over pixels and channels of sum_l y^2

    @classmethod
    def build(cls, data: dict, names: list[str], st: AdamSettings) -> "AdamProblem":
        """From the solve stage's loaded targets ``data`` ({target: (Transport, pooled, ok, y, use)})."""
        from objcam.envmap import EnvGrid
        from objcam.solvers.regularization import difference_operator

        tr = data[names[0]][0]
        use = np.logical_and.reduce([data[t][4] for t in names])
        rows = np.flatnonzero(use)
        Y = np.stack([data[t][3][rows] for t in names]).astype(np.float64)  # (L, M, 3)
        unknown = tr.unknown_albedo[rows]
        rho_known = np.clip(tr.albedo[rows].astype(np.float64), 1e-3, 1.0)
        Ap = tr.rho_free(rows)
        Ap = (Ap[0] if Ap.shape[0] == 1 else Ap.mean(axis=0)).astype(np.float64)  # (M, N) for init and prediction
        rho0 = np.where(unknown[:, None], 0.5, rho_known)
        # relative weights as the exact solve's: to mean(diag(A^T A)), A = diag(rho0) A'
        s_data = float(np.mean((rho0**2).mean(axis=1) @ (Ap * Ap)))
        D = difference_operator(EnvGrid(tr.env_height), tr.texel_index)
        G = None
        if st.lp > 0 and unknown.any():
            from objcam.solvers.joint import albedo_smoothness_operator

            G = albedo_smoothness_operator(tr.pixel_index[rows], tr.image_shape)
        return cls(tr=tr, pix=tr.pixel_index[rows], Y=Y, unknown=unknown, rho_known=rho_known, rho0=rho0, Ap=Ap,
                   DtD=(D.T @ D).tocsr(), ls=st.ls * s_data, lrr=st.lr_ridge * s_data, lp=st.lp, G=G,
                   t_data=float(np.sum(Y * Y) / (rows.size * 3)))

    def objective(self, X: np.ndarray, rho: np.ndarray) -> float:
        """F at envmaps X (L, N, 3) and albedo rho (M, 3) (held at rho_known where the albedo is known)."""
        rho = np.where(self.unknown[:, None], rho, self.rho_known)
        v = 0.0
        for l in range(self.Y.shape[0]):
            r = rho * (self.Ap @ X[l]) - self.Y[l]
            v += float(np.sum(r * r) + self.ls * np.sum(X[l] * (self.DtD @ X[l])) + self.lrr * np.sum(X[l] * X[l]))
        if self.G is not None:
            gr = self.G @ rho
            v += self.lp * self.t_data * float(np.sum(gr * gr))
        return v


def _bitmap_map(h: int, f: int) -> tuple[np.ndarray, np.ndarray]:
    """The linear map env (H, 2H, C) -> Mitsuba's envmap ``data`` (f H + 1, 2 f H + 2, C): row weights Wrow
    (f H + 1, H) and the texel column of every data column (2 f H + 2,)."""
    from objcam.render import mitsuba_box_bitmap

    w = 2 * h
    probe = np.zeros((h, 1, h), np.float32)
    probe[np.arange(h), 0, np.arange(h)] = 1.0  # channel k = one-hot texel row k
    wrow = mitsuba_box_bitmap(probe, f)[:, 0, :].astype(np.float64)  # (f H + 1, H)
    cols = (np.arange(w * f) // f)[::-1]  # objcam columns repeated f times, reversed for Mitsuba
    cols = np.concatenate([cols[-1:], cols, cols[:1]])  # Mitsuba's wrap columns
    return wrow, cols


def _sensor(mi, camera, f: int):
    c = camera
    if abs(c.fx - c.fy) > 1e-6 * c.fx or abs(c.cx - (c.width - 1) / 2) > 1e-3 or abs(c.cy - (c.height - 1) / 2) > 1e-3:
        raise StageError("method=adam needs a centred pinhole camera with square pixels (fx = fy, principal point "
                         "at the image centre)", fix="use solve.method=exact for this camera")
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # OpenCV (x right, y down) -> Mitsuba (x left, y up), z forward
    to_world = np.asarray(c.world_from_camera, dtype=np.float64) @ flip
    fov = float(np.degrees(2 * np.arctan(c.width / (2 * c.fx))))
    return {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "film": {"type": "hdrfilm", "width": c.width // f * f, "height": c.height // f * f,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent"}}


def solve_adam_targets(scene, data: dict, settings: AdamSettings) -> dict[str, AdamTargetResult]:
    """Run Adam for every target of a capture, one camera (transport group) at a time.

    scene: objcam.schemas.artifacts.SceneArtifact; data: {target: (Transport, pooled, pooled_ok, y (M, 3), use (M,))}
    as the solve stage loads them. Returns {target: AdamTargetResult}.
    """
    groups: dict[str, list[str]] = {}
    for t in scene.targets:
        groups.setdefault(str(data[t.name][0].folder), []).append(t.name)
    out: dict[str, AdamTargetResult] = {}
    for names in groups.values():
        out.update(_solve_camera(scene, data, names, settings))
    return out


def _solve_camera(scene, data, names, st: AdamSettings) -> dict[str, AdamTargetResult]:
    import drjit as dr

    from objcam.envmap import EnvGrid
    from objcam.scene import build_mitsuba_scene, use_mitsuba

    mi = use_mitsuba()
    if not mi.variant().endswith("_ad_rgb"):
        raise StageError(f"method=adam needs Mitsuba's llvm_ad_rgb variant (have {mi.variant()})",
                         fix="run `make setup` (installs libllvm19)")
    pb = AdamProblem.build(data, names, st)
    tr, grid, f = pb.tr, EnvGrid(pb.tr.env_height), pb.tr.downsample
    hp, wp = tr.image_shape
    pix, Y, L, m, unknown, rho_known, Ap = pb.pix, pb.Y, pb.Y.shape[0], pb.pix.size, pb.unknown, pb.rho_known, pb.Ap
    rho0, DtD, ls, lrr, G, t_data = pb.rho0, pb.DtD, pb.ls, pb.lrr, pb.G, pb.t_data
    wrow, cols = _bitmap_map(grid.height, st.upsample)

    desc = scene.description
    sc = build_mitsuba_scene(desc, scene.folder, envmap=np.ones(grid.shape + (3,), np.float32), unknown_albedo=1.0,
                             extra={"sensor": _sensor(mi, tr.camera, f),
                                    "integrator": {"type": "prb", "max_depth": int(st.max_depth)}})
    params = mi.traverse(sc)
    key = next(k for k in params.keys() if k.endswith(".data") and "emitter" in k.lower()) if "emitter.data" \
        not in params.keys() else "emitter.data"

    n = tr.texel_index.size
    x0 = float(np.mean(Y)) / max(float(np.mean(rho0 * (Ap @ np.ones(n))[:, None])), 1e-30)
    theta = np.full((L, n, 3), np.log(max(x0, 1e-12)))
    phi = np.log(rho0 / (1 - np.minimum(rho0, 1 - 1e-6)))
    mom = [np.zeros_like(theta), np.zeros_like(phi)]
    vel = [np.zeros_like(theta), np.zeros_like(phi)]
    b1, b2, eps = 0.9, 0.999, 1e-8
    t_start = time.perf_counter()
    hist: list[float] = []
    it = 0
    stop = "max_iter"
    lr_now, best_win, stall, lr_drops = st.lr, np.inf, 0, []
    hist_exact: list[tuple[int, float]] = []

    def exact_objective() -> float:
        # noise-free, with the transport matrix instead of a render (see AdamProblem.objective)
        return pb.objective(np.exp(theta), 1.0 / (1.0 + np.exp(-phi)))  # known pixels are held by objective()

    hist_exact.append((0, exact_objective()))  # the start, so the history shows what the run gained
    hist_seconds = [0.0]  # the wall time of each entry of hist_exact
    plateau: tuple[int, float] | None = None  # (iteration, seconds) where the plateau rule fired
    while it < st.max_iter:
        if time.perf_counter() - t_start > st.seconds:
            stop = "time budget"
            break
        x = np.exp(theta)
        rho = np.where(unknown[:, None], 1.0 / (1.0 + np.exp(-phi)), rho_known)
        rho_r = np.where(unknown[:, None], rho, 1.0)  # what multiplies the render
        g_theta = np.zeros_like(theta)
        g_rho = np.zeros_like(rho)
        loss = 0.0
        for l in range(L):
            env = np.zeros((grid.n_texels, 3))
            env[tr.texel_index] = x[l]
            env = env.reshape(grid.height, grid.width, 3)
            bitmap = np.einsum("rh,hwc->rwc", wrow, env[:, cols])
            tensor = mi.TensorXf(padded(bitmap, np.float32))  # objcam.dr_memory
            dr.enable_grad(tensor)
            params[key] = tensor
            params.update()
            img = mi.render(sc, params, spp=st.spp, seed=st.seed + it * L + l)
            im = np.asarray(img, dtype=np.float64)[: hp * f, : wp * f]
            pooled = im.reshape(hp, f, wp, f, 3).mean(axis=(1, 3)).reshape(-1, 3)
            s = pooled[pix]
            # the render holds the known albedos already (the scene is built with them; unknown ones at 1), so
            # only the estimated albedo multiplies it: the model is rho * A' x in both cases
            r = rho_r * s - Y[l]
            loss += float(np.sum(r * r))
            g_rho += 2 * r * s
            adj = np.zeros((hp * wp, 3))
            adj[pix] = 2 * r * rho_r / (f * f)
            adj = np.repeat(np.repeat(adj.reshape(hp, wp, 3), f, axis=0), f, axis=1)
            dr.backward(dr.sum(img * mi.TensorXf(padded(adj, np.float32)), axis=None))
            gb = np.asarray(dr.grad(tensor), dtype=np.float64)  # (f H + 1, 2 f H + 2, 3)
            g_env = np.zeros((grid.height, grid.width, 3))
            gcol = np.zeros((gb.shape[0], grid.width, 3))
            np.add.at(gcol, (slice(None), cols), gb)
            g_env = np.einsum("rh,rwc->hwc", wrow, gcol)
            g_x = g_env.reshape(-1, 3)[tr.texel_index]
            # the same envmap priors as the exact solve
            g_x += 2 * ls * (DtD @ x[l]) + 2 * lrr * x[l]
            loss += float(ls * np.sum(x[l] * (DtD @ x[l])) + lrr * np.sum(x[l] * x[l]))
            g_theta[l] = g_x * x[l]
        if G is not None:
            gr = G @ rho
            loss += st.lp * t_data * float(np.sum(gr * gr))
            g_rho += 2 * st.lp * t_data * (G.T @ gr)
        g_phi = np.where(unknown[:, None], g_rho * rho * (1 - rho), 0.0)
        if not np.isfinite(loss):
            raise StageError(f"method=adam diverged at iteration {it} (non-finite loss)",
                             fix="lower solve.adam_lr")
        hist.append(loss)
        it += 1
        for k, (p, g) in enumerate(((theta, g_theta), (phi, g_phi))):
            mom[k] = b1 * mom[k] + (1 - b1) * g
            vel[k] = b2 * vel[k] + (1 - b2) * g * g
            p -= lr_now * (mom[k] / (1 - b1**it)) / (np.sqrt(vel[k] / (1 - b2**it)) + eps)
        if it % st.window == 0:
            cur = exact_objective()
            hist_exact.append((it, cur))
            hist_seconds.append(time.perf_counter() - t_start)
            if cur < best_win * (1 - st.converge_tol):
                best_win, stall = cur, 0
            else:
                stall += 1
            if stall >= st.patience:
                if lr_now > st.lr / 16 * 1.0001:
                    lr_now, stall = 0.5 * lr_now, 0
                    lr_drops.append(it)
                elif plateau is None:
                    plateau = (it, time.perf_counter() - t_start)
                    if st.stop_on_plateau:
                        stop = "converged"
                        break
                    stall = 0  # told to go on: at the smallest rate until the budget
    seconds = time.perf_counter() - t_start
    if hist_exact[-1][0] != it:
        hist_exact.append((it, exact_objective()))  # and the end
        hist_seconds.append(seconds)
    x = np.exp(theta)
    rho = np.where(unknown[:, None], 1.0 / (1.0 + np.exp(-phi)), rho_known)
    out = {}
    for l, name in enumerate(names):
        env = np.zeros((grid.n_texels, 3), np.float32)
        env[tr.texel_index] = x[l]
        pred = np.zeros((hp * wp, 3), np.float32)
        fit = rho * (Ap @ x[l])
        pred[pix] = fit
        alb = alb_mask = None
        if unknown.any():
            alb = np.zeros((hp * wp, 3), np.float32)
            alb[pix] = rho
            alb_mask = np.zeros(hp * wp, bool)
            alb_mask[pix[unknown]] = True
            alb, alb_mask = alb.reshape(hp, wp, 3), alb_mask.reshape(hp, wp)
        rel = float(np.linalg.norm(fit - Y[l]) / max(np.linalg.norm(Y[l]), 1e-30))
        info = {"method": "adam", "albedo": "unknown" if unknown.any() else "known",
                "scale_ambiguous": bool(unknown.any()), "texels": int(n), "pixels_used": int(m),
                "solve_seconds": round(seconds, 3), "iterations": it, "stopped": stop, "lr_halved_at": lr_drops,
                "loss_history": [float(v) for v in hist],
                "objective_history_transport": [[int(i), float(v)] for i, v in hist_exact],
                "objective_history_seconds": [round(float(v), 3) for v in hist_seconds],
                "plateau_iteration": None if plateau is None else plateau[0],
                "plateau_seconds": None if plateau is None else round(plateau[1], 3),
                "kkt_residual_max": float("nan"),
                "relative_image_residual": rel, "lr": st.lr, "spp": st.spp, "max_depth": st.max_depth,
                "ls_relative": st.ls, "lr_relative": st.lr_ridge, "lp_relative": st.lp}
        out[name] = AdamTargetResult(env.reshape(grid.height, grid.width, 3), pred.reshape(hp, wp, 3), alb,
                                     alb_mask, info)
    return out
