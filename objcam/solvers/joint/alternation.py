"""The alternation of the joint solve: sweeps of block steps, the stopping rule and the divergence guard.

Exact alternation (``method="exact"``): block-coordinate descent, each block solved exactly, so the objective is
non-increasing (``JointResult.step_history`` records it after every sub-step): the x-step
(:mod:`objcam.solvers.joint.x_step`), the rho-step (:mod:`objcam.solvers.joint.rho_step`) and the scale step
(:mod:`objcam.solvers.joint.scale_step`). The loop is x, then {rho, scale, x} until every channel's relative
objective decrease over one sweep is below ``tol`` or ``max_iter`` sweeps; ending on an x-step makes the returned x
exactly optimal for the returned rho (``kkt_x`` ~ 1e-10) while ``kkt_rho`` measures how far the alternation still is
from a stationary point. The safeguarded accelerations (:mod:`objcam.solvers.joint.accelerate`) only propose
points that are kept when they beat the plain block step, so they keep it monotone.

Stopping rule: a sweep is {rho-step, subspace proposal, scale step, (Anderson-extrapolated) x-step,
majorise-minimise x-steps}; the solve stops when the relative decrease of the objective over one sweep is below
``tol`` (per channel with the quadratic prior; of the total with the edge prior, whose edges couple the channels)
or after ``max_iter`` sweeps.

The paper's variant (``method="paper"``): the same loop with the method's damped clipped steps instead of exact
block minimisation and no scale step: ``x <- max(0, x - alpha Q_c^{-1} (Q_c x - b))`` (Eq. 7, one step per
sweep) and ``rho <- clip(rho - beta H^{-1} (H rho - beta_rhs), rho_min, 1)``. It is not monotone (it stops
when the relative change of the objective is below ``tol``). If the objective becomes non-finite or exceeds
``diverge_factor`` x the best so far (e.g. ``alpha`` > 2 overshoots), the solve stops, returns the best
(last good) estimate seen and says so (``diverged``, ``message``). The same guard protects the exact variant
(which, being monotone, only trips on non-finite numbers).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from objcam.solvers.joint.accelerate import Anderson, SubspaceGN
from objcam.solvers.joint.context import StepContext
from objcam.solvers.joint.rho_step import rho_step
from objcam.solvers.joint.scale_step import pinned_scale, scale_step
from objcam.solvers.joint.x_step import x_step, x_step_pcg
from objcam.threads import single_blas_thread


class _Snapshot(NamedTuple):
    """The best point seen (for the divergence guard): its total objective, x, rho, shading, objective (C,),
    kkt_x (L, C) and sweep."""

    total: float
    X: np.ndarray
    rho: list[np.ndarray]
    S: list[np.ndarray]
    obj: np.ndarray
    kkt_x: np.ndarray
    sweep: int


class Alternation:
    """One run of the alternation on ``ctx.J``; :meth:`run` leaves the solution in its attributes.

    The current point: ``rho`` (list of (M_p, C)), ``X`` (N, L, C), the shading ``S`` (list of (M_p, L, C)), its
    objective ``obj_t`` (C,) and ``kkt_x`` (L, C). The record: ``step_hist`` (total objective after every
    sub-step), ``hist`` (objective (C,) after the first x-step and after every sweep), ``iters``, ``converged``,
    ``diverged``, ``message``, ``kkt_rho`` (P, C), ``rmax`` (C,) (largest albedo per channel) and ``stats``
    (accelerations accepted and rejected, float64 redos, majorise-minimise steps).
    """

    def __init__(self, ctx: StepContext, *, tol: float, max_iter: int, scale_step: bool, accelerate: bool,
                 anderson_depth: int, gn_rank: int, gn_inner: int, diverge_factor: float, edge_steps: int,
                 polish: bool, pinned: bool = True):
        self.ctx = ctx
        self.tol, self.max_iter, self.scale_step = tol, max_iter, scale_step
        self.accelerate = accelerate and ctx.exact
        self.anderson_depth, self.gn_rank, self.gn_inner = anderson_depth, gn_rank, gn_inner
        self.diverge_factor, self.edge_steps, self.polish = diverge_factor, edge_steps, polish
        self.pinned = pinned
        self.pinned_info: dict | None = None
        J = ctx.J
        self.splits = np.cumsum([A.shape[0] for A in J.As])[:-1]
        self.fixed_flat = np.concatenate(J.fixed)  # the pixels of known albedo, in the order of _flat()
        self.gn: SubspaceGN | None = None
        self.diverged = False
        self.converged = False
        self.message = ""
        self.iters = 0

    # ---------------------------------------------------------------------------------------------- helpers
    def _total(self, rho, X, S) -> float:
        return float(self.ctx.J.true_objective(rho, X, S).sum())

    def _flat(self, rho, c):
        return np.concatenate([r[:, c] for r in rho])

    def _unflat(self, z, rho, c):
        for r, part in zip(rho, np.split(z, self.splits)):
            r[:, c] = part

    # ---------------------------------------------------------------------------------------------- the run
    def run(self, rho_init: Sequence[np.ndarray] | None) -> None:
        """Sweep 0 (the first x-step), the sweeps, the final polished x-step; one BLAS thread throughout."""
        J = self.ctx.J
        with single_blas_thread():
            self._start(rho_init)
            for it in range(1, self.max_iter + 1):
                if self._sweep(it):
                    break
            self._finish()
            self.kkt_rho = J.rho_kkt(self.rho, self.S)
            self.rmax = np.max([r.max(axis=0) for r in self.rho if r.shape[0]], axis=0)

    def _start(self, rho_init) -> None:
        """The initial albedo, x for it (quadratic prior; the edge prior takes its scale from this x), and the
        subspace Gauss-Newton basis from that x-step's Gram matrix."""
        ctx, J = self.ctx, self.ctx.J
        n, L, C = J.n, J.L, J.C
        rho = J.initial_rho() if rho_init is None else J.pin([
            np.clip(np.asarray(r, dtype=np.float64).reshape(A.shape[0], C), J.rho_min, 1.0).copy()
            for r, A in zip(rho_init, J.As)])
        X = np.zeros((n, L, C))
        S = [np.zeros((A.shape[0], L, C)) for A in J.As]
        self.step_hist = [self._total(rho, X, S)]
        self.per_channel = not (J.prior == "edges")  # the shared edges couple the channels: stop on the total
        self.active = np.ones(C, dtype=bool)
        self.aa = [Anderson(self.anderson_depth) for _ in range(C)]
        self.stats = dict(accepted=0, rejected=0, float64_redo=0, gn_accepted=0, gn_rejected=0, mm_steps=0)
        # sweep 0: x for the initial albedo (quadratic prior); the edge prior takes its scale from this x
        X, kkt_x = x_step(ctx, rho, X, np.arange(C), warm=False)
        S = J.shading(X)
        if J.prior == "edges":
            J.start_huber(X)  # F is the Huber objective from here: the histories start at this point
            if J.huber_on:
                self.step_hist = []
        obj_t = J.true_objective(rho, X, S)
        self.step_hist.append(float(obj_t.sum()))
        self.hist = [obj_t.copy()]
        if ctx.exact and self.gn_rank and self.gn_rank > 0:
            # its basis: the top eigenvectors of the first sweep's Gram matrix (the data's strong directions)
            K0 = (ctx.pcg.grams.get(0) if ctx.use_pcg
                  else J.gram(rho, 0, ctx.gram_cache, fast=ctx.fast_gram))  # cached
            self.gn = SubspaceGN(J, self.gn_rank, ctx.fast_gram, K=K0)
        self.best = _Snapshot(float(obj_t.sum()), X.copy(), [r.copy() for r in rho], [s.copy() for s in S],
                              obj_t.copy(), kkt_x.copy(), 0)
        self.rho, self.X, self.S, self.obj_t, self.kkt_x = rho, X, S, obj_t, kkt_x

    # --------------------------------------------------------------------------------------------- one sweep
    def _sweep(self, it: int) -> bool:
        """Sweep ``it`` on the channels still active; True when the solve should stop."""
        ctx, J = self.ctx, self.ctx.J
        ctx.gram_cache.clear()
        chans = np.flatnonzero(self.active)
        prev = self.obj_t.copy()
        # plain block steps: rho, then scale (x follows below); per-channel decisions compare the objective
        # with the quadratic prior in use (for edges: the majoriser at the tangent point, so F decreases too)
        rho_p = rho_step(ctx, self.rho, self.S, chans)
        obj_r = J.objective(rho_p, self.X, self.S)
        Xs, Ss = self.X.copy(), [s.copy() for s in self.S]
        if self.gn is not None:
            self._subspace_proposals(chans, rho_p, obj_r, Xs, Ss)
        self.step_hist.append(self._total(rho_p, Xs, Ss))
        if ctx.exact and self.scale_step:
            scale_step(ctx, rho_p, Xs, Ss, chans)
            self.step_hist.append(self._total(rho_p, Xs, Ss))
        J.tangent(Xs)
        obj_s = J.objective(rho_p, Xs, Ss)
        plain = list(chans)
        new_X, new_kkt = Xs, self.kkt_x.copy()  # new_X is Xs: accepted channels are written into it in place
        new_rho = [r.copy() for r in rho_p]
        if self.accelerate:
            self._anderson(chans, rho_p, Xs, obj_s, plain, new_X, new_kkt, new_rho)
        if plain:
            self._plain_x_step(plain, new_rho, Xs, obj_s, new_X, new_kkt)
        self.rho, self.X, self.kkt_x = new_rho, new_X, new_kkt
        if J.huber_on and ctx.exact:
            self._majorise_minimise(chans)
        J.tangent(self.X)
        self.S = J.shading(self.X)
        self.obj_t = J.true_objective(self.rho, self.X, self.S)
        tot = float(self.obj_t.sum())
        self.step_hist.append(tot)
        self.hist.append(self.obj_t.copy())
        self.iters = it
        if self._guard(it, tot):
            return True
        return self._stopping_rule(prev, tot)

    def _subspace_proposals(self, chans, rho_p, obj_r, Xs, Ss) -> None:
        """Subspace Gauss-Newton proposals for x, each followed by the exact rho-step; kept while they beat the
        plain rho-step (the same x-step follows either way, so the objective stays monotone). Updates rho_p,
        obj_r, Xs and Ss in place on the channels where a proposal won."""
        ctx, J = self.ctx, self.ctx.J
        t0 = time.perf_counter()
        todo_ch = list(chans)
        for inner in range(self.gn_inner):
            if not todo_ch:
                break
            b_rho, b_X, b_S = (self.rho, self.X, self.S) if inner == 0 else (rho_p, Xs, Ss)
            dX = self.gn.direction(b_rho, b_X, b_S, todo_ch)
            remaining, improved = list(todo_ch), []
            for t in (1.0, 0.5, 0.25):
                if not remaining:
                    break
                Xt = b_X.copy()
                Xt[:, :, remaining] = np.maximum(b_X[:, :, remaining] + t * dX[:, :, remaining], 0.0)
                St = J.shading(Xt)
                rt = rho_step(ctx, b_rho, St, np.array(remaining))
                ot = J.objective(rt, Xt, St)
                for c in list(remaining):
                    if ot[c] < obj_r[c]:
                        remaining.remove(c)
                        # keep going only while a proposal still buys a useful decrease
                        if obj_r[c] - ot[c] > 10 * self.tol * obj_r[c]:
                            improved.append(c)
                        Xs[:, :, c] = Xt[:, :, c]
                        for k in range(J.P):
                            Ss[k][:, :, c] = St[k][:, :, c]
                            rho_p[k][:, c] = rt[k][:, c]
                        obj_r[c] = ot[c]
                        self.stats["gn_accepted"] += 1
            self.stats["gn_rejected"] += len(remaining)
            todo_ch = improved
        ctx.timers["gn"] += time.perf_counter() - t0

    def _anderson(self, chans, rho_p, Xs, obj_s, plain, new_X, new_kkt, new_rho) -> None:
        """Try the Anderson-extrapolated albedo with its exact x-step; on the channels where it beats the plain
        steps' objective ``obj_s`` take it (into new_X, new_kkt, new_rho; removed from ``plain``), elsewhere
        restart that channel's history."""
        ctx, J = self.ctx, self.ctx.J
        cand = [r.copy() for r in rho_p]
        tried = []
        for c in chans:
            z = self.aa[c].step(self._flat(self.rho, c), self._flat(rho_p, c))
            if z is not None:
                z = np.clip(z, J.rho_min, 1.0)
                z = np.where(self.fixed_flat, self._flat(rho_p, c), z)  # extrapolate the free pixels only
                if np.max(np.abs(z - self._flat(rho_p, c))) > 1e-12:
                    self._unflat(z, cand, c)
                    tried.append(c)
        if tried:
            Xa, ka = x_step(ctx, cand, Xs, np.array(tried), warm=True)
            Sa = J.shading(Xa)
            obj_a = J.objective(cand, Xa, Sa)
            for c in tried:
                if obj_a[c] <= obj_s[c]:
                    plain.remove(c)
                    new_X[:, :, c] = Xa[:, :, c]
                    new_kkt[:, c] = ka[:, c]
                    self._unflat(self._flat(cand, c), new_rho, c)
                    self.stats["accepted"] += 1
                else:
                    self.aa[c].reset()
                    self.stats["rejected"] += 1

    def _plain_x_step(self, plain, new_rho, Xs, obj_s, new_X, new_kkt) -> None:
        """The x-step of the channels ``plain`` at new_rho (into new_X, new_kkt), redone in float64 where the
        float32 Gram raised the objective."""
        ctx, J = self.ctx, self.ctx.J
        Xp, kp = x_step(ctx, new_rho, Xs, np.array(plain), warm=True)
        if ctx.fast_gram and ctx.exact and not ctx.use_pcg:
            # the float32 Gram could in principle cost a hair of objective: check, redo in float64
            obj_p = J.objective(new_rho, Xp, J.shading(Xp))
            redo = [c for c in plain if obj_p[c] > obj_s[c]]
            if redo:
                X64, k64 = x_step(ctx, new_rho, Xs, np.array(redo), warm=True, fast=False)
                for c in redo:
                    Xp[:, :, c], kp[:, c] = X64[:, :, c], k64[:, c]
                self.stats["float64_redo"] += len(redo)
        for c in plain:
            new_X[:, :, c] = Xp[:, :, c]
            new_kkt[:, c] = kp[:, c]

    def _majorise_minimise(self, chans) -> None:
        """Edge prior: more majorise-minimise x-steps on this sweep's Gram matrices (factorisations only): each one
        minimises the majoriser at the current point exactly, so F decreases."""
        ctx, J = self.ctx, self.ctx.J
        rho = self.rho
        self.step_hist.append(self._total(rho, self.X, J.shading(self.X)))
        for _ in range(self.edge_steps - 1):
            J.tangent(self.X)
            Xm, km = x_step(ctx, rho, self.X, chans, warm=True)
            Sm = J.shading(Xm)
            fm, fx = self._total(rho, Xm, Sm), self.step_hist[-1]
            self.stats["mm_steps"] += 1
            if not fm <= fx:  # float32 Gram rounding: keep the better point
                break
            self.X, self.kkt_x = Xm, km
            self.step_hist.append(fm)
            if fx - fm <= 0.1 * self.tol * fx:
                break

    # ---------------------------------------------------------------------------------------- when to stop
    def _guard(self, it: int, tot: float) -> bool:
        """The divergence guard: remember the best point; True (diverged) when the objective is non-finite or
        above ``diverge_factor`` x the best."""
        if np.isfinite(tot) and tot < self.best.total:
            self.best = _Snapshot(tot, self.X.copy(), [r.copy() for r in self.rho], [s.copy() for s in self.S],
                                  self.obj_t.copy(), self.kkt_x.copy(), it)
        if not np.isfinite(tot) or tot > self.diverge_factor * self.best.total:
            why = ("non-finite objective" if not np.isfinite(tot) else
                   f"objective {tot:.6g} > {self.diverge_factor:g} x best {self.best.total:.6g}")
            self.diverged = True
            self.message = (f"diverged at sweep {it} ({why}); returning the last good estimate, from sweep "
                            f"{self.best.sweep} (objective {self.best.total:.6g})")
            return True
        return False

    def _stopping_rule(self, prev: np.ndarray, tot: float) -> bool:
        """Retire the channels whose relative decrease over the sweep fell below tol (all of them at once with the
        edge prior: its total); True when none is left."""
        tol, exact = self.tol, self.ctx.exact
        if self.per_channel:
            dec = (prev - self.obj_t) / np.where(prev > 0, prev, 1.0)
            done = np.abs(dec) < tol if not exact else dec < tol
        else:
            p_tot = float(prev.sum())
            dec_t = (p_tot - tot) / (p_tot if p_tot > 0 else 1.0)
            done = np.full(self.ctx.J.C, abs(dec_t) < tol if not exact else dec_t < tol)
        self.active &= ~done
        return not self.active.any()

    # ------------------------------------------------------------------------------------------- the end
    def _finish(self) -> None:
        """Back to the best point if diverged; else the final x-step (for edges: at the final tangent point),
        polished against the exact float64 operator with the last sweep's float32 Gram matrices (formed at this
        albedo) as the preconditioner: x exactly optimal (KKT ~ qp_tol) for the final rho and the quadratic prior
        in use."""
        ctx, J = self.ctx, self.ctx.J
        self.converged = (not self.diverged) and not self.active.any()
        moved = False
        if self.diverged:
            b = self.best
            self.X, self.rho, self.S, self.obj_t, self.kkt_x = b.X, b.rho, b.S, b.obj, b.kkt_x
        elif ctx.exact and self.pinned and J.any_fixed:
            # the scale the pixels of known albedo pin, by the data alone (scale_step.pinned_scale: the priors
            # would shrink it); F may rise, so the histories (the alternation's descent) stop before it
            before = float(self.obj_t.sum())
            factors = pinned_scale(ctx, self.rho, self.X, self.S)
            moved = any(f != 1.0 for f in factors)
            self.obj_t = J.true_objective(self.rho, self.X, self.S)
            self.pinned_info = {"factors": [float(f) for f in factors], "objective_before": before,
                                "objective_after": float(self.obj_t.sum())}
        if not self.diverged and ctx.exact and self.polish and (ctx.fast_gram or ctx.use_pcg or J.huber_on or moved):
            J.tangent(self.X)
            rho = self.rho
            pre = {c: J.gram(rho, c, ctx.gram_cache, fast=ctx.fast_gram) for c in range(J.C)}  # cached: no new Gram
            Xf, kf = x_step_pcg(ctx, rho, self.X, np.arange(J.C), warm=True, grams=pre)
            Sf = J.shading(Xf)
            ff = self._total(rho, Xf, Sf)
            if ff <= float(self.obj_t.sum()) * (1 + 1e-12):
                self.X, self.kkt_x, self.S = Xf, kf, Sf
                self.obj_t = J.true_objective(rho, self.X, self.S)
                if moved:  # the x-step at the pinned scale's albedo: exact for it, recorded beside the histories
                    self.pinned_info["objective_polished"] = float(self.obj_t.sum())
                else:
                    self.step_hist.append(float(self.obj_t.sum()))
                    self.hist[-1] = self.obj_t.copy()
        if not self.message:
            self.message = (
                f"converged after {self.iters} sweeps (relative decrease < {self.tol:g})" if self.converged else
                f"stopped at max_iter = {self.max_iter} sweeps before the relative decrease fell below {self.tol:g}")
