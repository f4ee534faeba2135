"""Light sources the ball shows saturated in every bracket frame (the sun, a bare lamp): where they are and the
energy the probe holds for them, which is a LOWER BOUND (the merge kept the shortest frame's clipped value).

A saturated source is a 4-connected region (wrapping in azimuth) of fine texels flagged ``SATURATED`` by
:func:`objcam.probe.unwrap.unwrap`. Its energy is ``sum(radiance x solid angle)`` over the region, per channel, in
the probe's radiance units times steradians. Nothing here extrapolates the clipped profile: every number is
labelled a lower bound so no one mistakes it for a measurement.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from objcam.envmap import EnvGrid, direction_to_spherical
from objcam.metrics import LUMA
from objcam.probe.unwrap import ProbeEnvmap

LOWER_BOUND_LABEL = ("lower bound: saturated in every bracket frame (the true energy is higher; shoot shorter "
                     "exposures, or an ND filter, to measure it)")


def _wrapped_labels(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """4-connected labels of ``mask`` (H, W) bool with the first and last columns joined (azimuth wraps)."""
    lab, n = ndimage.label(mask)
    if n == 0:
        return lab, 0
    parent = np.arange(n + 1)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in zip(lab[:, 0], lab[:, -1]):
        if a and b:
            ra, rb = find(int(a)), find(int(b))
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([find(i) for i in range(n + 1)])
    uniq, relab = np.unique(roots, return_inverse=True)
    return relab.reshape(-1)[lab.reshape(-1)].reshape(lab.shape), len(uniq) - 1


def saturated_sources(probe: ProbeEnvmap, max_sources: int = 8) -> list[dict]:
    """The saturated regions of a fine probe, brightest (lower-bound energy) first, at most ``max_sources``.

    Each: ``direction`` (3,) unit world vector (luminance x solid-angle weighted mean), ``theta_deg``/``phi_deg``
    (objcam's lat-long angles), ``solid_angle_sr``, ``texels``, ``energy_lower_bound`` (3,) radiance units x sr,
    ``peak_radiance_lower_bound`` (3,), ``label`` (says it is a lower bound).
    """
    sat = probe.saturated
    if not sat.any():
        return []
    lab, n = _wrapped_labels(sat)
    grid = EnvGrid(sat.shape[0])
    w = grid.solid_angles()
    d = grid.directions()
    env = probe.envmap.astype(np.float64)
    lum = env @ LUMA
    out = []
    for k in range(1, n + 1):
        m = lab == k
        wk = w[m]
        energy = (env[m] * wk[:, None]).sum(axis=0)
        weight = np.maximum(lum[m], 0) * wk
        if weight.sum() <= 0:
            weight = wk
        mean = (d[m] * weight[:, None]).sum(axis=0)
        mean /= max(np.linalg.norm(mean), 1e-300)
        theta, phi = direction_to_spherical(mean)
        out.append({"direction": mean.tolist(), "theta_deg": float(np.degrees(theta)),
                    "phi_deg": float(np.degrees(phi)), "solid_angle_sr": float(wk.sum()), "texels": int(m.sum()),
                    "energy_lower_bound": energy.tolist(), "peak_radiance_lower_bound": env[m].max(axis=0).tolist(),
                    "label": LOWER_BOUND_LABEL})
    out.sort(key=lambda s: -float(np.dot(s["energy_lower_bound"], LUMA)))
    return out[:max_sources]
