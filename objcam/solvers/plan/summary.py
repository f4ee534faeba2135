"""The solve's one-line summary and stage metrics, from every target's solve.json record: what was solved, how
exactly, and a warning first where the result cannot be trusted (a diverged damped solve, an envmap that only the
priors determine)."""

from __future__ import annotations

from objcam.solvers.plan.verdict import GRADES


def solve_summary(per_target: dict[str, dict], method: str, total: float) -> tuple[str, dict]:
    """(the summary line, the stage metrics) for ``per_target`` {target: solve.json} solved by ``method`` in
    ``total`` seconds."""
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
    red = {k: v["verdict"]["reasons"][0] for k, v in per_target.items()
           if (v.get("verdict") or {}).get("grade") == "red" and k not in free}
    summary = ((f"WARNING: joint solve ({method}) {div['message']}; fix: use solve.method=exact (monotone) "
                "or a smaller solve.alpha. " if div else "")
               + (f"WARNING: {', '.join(free)}: one illumination and every albedo unknown, so the albedo alone can "
                  "explain the photo and the envmap comes from the priors, not the data; fix: give the support's or "
                  "the object's albedo in capture.toml [albedo] (a value, or \"uniform\" for one colour), or "
                  + ("photograph two or more illuminations. "
                     if len({per_target[k].get("illumination", k) for k in free}) < 2 else
                     "photograph these illuminations from one camera position: each has a camera of its own, and "
                     "only targets of one camera are solved together (give them one camera file; sfm merges poses "
                     "within sfm.same_position_px). ")
                  if free else "")
               + "".join(f"WARNING: {k} graded red: {why}. " for k, why in red.items())
               + f"{len(per_target)} target(s), {method}"
               + ((", joint albedo + envmap (envmap known only up to scale)" if ambiguous else
                   ", joint albedo + envmap (scale fixed by the pixels of known albedo)") if joint else "")
               + (f", {n_mixed} silhouette pixels left out" if n_mixed else "")
               + (f", support light redone {n_refit}x from the estimated albedo" if n_refit else "")
               + (f", final step: {n_final} round(s) of the albedo's TV step and the envmaps at it" if n_final else "")
               + sources_phrase(per_target)
               + sky_profile_phrase(per_target)
               + f", {total:.2f} s; KKT residual <= {worst_kkt:.1e}; "
               + ", ".join(f"{k}: image residual {v['relative_image_residual']:.3f}"
                           + (f", {v['verdict']['grade']}" if v.get("verdict") else "") for k, v in per_target.items()))
    metrics = {"targets": per_target, "seconds": round(total, 4)}
    grades = [v["verdict"]["grade"] for v in per_target.values() if v.get("verdict")]
    if grades:  # the capture's worst grade
        metrics["verdict"] = max(grades, key=GRADES.index)
    if joint:
        metrics["scale_ambiguous"] = ambiguous
    return summary, metrics


def sources_phrase(per_target: dict[str, dict]) -> str:
    """solve.sources=compact (objcam.solvers.sources): ", N bright blob(s) collapsed to point sources" or ""."""
    rec = [(v.get("edges") or {}).get("sources") for v in per_target.values()]
    rec = [r for r in rec if r]
    if not rec:
        return ""
    n, found = sum(r["collapsed"] for r in rec), sum(r["blobs_found"] for r in rec)
    if not n:
        return ""
    return f", {n} of {found} bright blob(s) moved into one or two texels (the photo places them there)"


def sky_profile_phrase(per_target: dict[str, dict]) -> str:
    """solve.sky_profile=auto (objcam.solvers.skyprofile): ", the sky outside the bright sources solved as one value
    per elevation row for T1, T2 (...)" or ""."""
    taken = [k for k, v in per_target.items() if ((v.get("edges") or {}).get("sky_profile") or {}).get("taken")]
    if not taken:
        return ""
    return (f", the sky outside the bright sources solved as one value per elevation row for {', '.join(taken)} "
            "(the photo could not tell its azimuthal detail from none)")

