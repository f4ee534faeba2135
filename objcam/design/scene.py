"""One shared setup for every occluder: the plane z = 0, one camera looking at the origin, and the direct-light
transport A of each occluder built by :func:`objcam.transport.build.build_camera` (the transport stage's own
code, model ``direct``), so the designs are scored with exactly the A a capture would get."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from objcam.camera import Camera, look_at
from objcam.design.params import DesignParams
from objcam.scene import AlbedoValue, MeshData, SceneDescription, make_plane
from objcam.transport.storage import Transport


def design_camera(p: DesignParams) -> Camera:
    """The shared square pinhole camera: ``distance * size`` metres from the origin at ``elevation_deg`` and
    ``azimuth_deg``, looking at the origin (the occluder's foot), horizontal field of view ``fov_deg``."""
    az, el = math.radians(p.azimuth_deg), math.radians(p.elevation_deg)
    d = p.distance * p.size
    eye = d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    f = (p.image_size / 2) / math.tan(math.radians(p.fov_deg) / 2)
    c = (p.image_size - 1) / 2
    return Camera(width=p.image_size, height=p.image_size, fx=f, fy=f, cx=c, cy=c,
                  world_from_camera=look_at(eye, np.zeros(3)).tolist())


def reference_scale(p: DesignParams, camera: Camera) -> float:
    """``s_ref``: the mean over upper-hemisphere texels of the squared column norm of A for the plane alone (no
    occluder) seen by ``camera``; one pixel per pixel centre that hits the plane (radiance^2 per unit
    envmap radiance^2).

    Unoccluded, a plane pixel's column is ``rho / pi * W_z(j)`` with ``W_z(j)`` the integral of cos(theta) over
    texel j (exact), so ``s_ref = M_plane (rho / pi)^2 mean_j W_z(j)^2``. It depends on the setup only, so
    ``lr * s_ref`` is one absolute ridge weight for every occluder: their uncertainties compare directly.
    """
    from objcam.transport.direct import TexelTable

    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    o, d = camera.rays(u.ravel(), v.ravel())
    down = d[:, 2] < -1e-12
    t = np.where(down, -o[:, 2] / np.where(down, d[:, 2], -1.0), np.inf)
    hit = o[:, :2] + t[:, None] * d[:, :2]
    m_plane = int(np.count_nonzero(down & np.all(np.abs(hit) <= p.plane_size / 2, axis=1)))
    tab = TexelTable.of(p.env_height)
    wz = tab.wvec[:, 2]
    upper = tab.dirs[:, 2] > 0
    return float(m_plane * (p.support_albedo / np.pi) ** 2 * np.mean(wz[upper] ** 2))


def build_transport(mesh: MeshData, p: DesignParams, camera: Camera) -> tuple[Transport, dict]:
    """The direct-light A (1 channel: grey albedos) of ``mesh`` on the plane seen by ``camera``, and the
    transport build's metrics. Built in a temporary folder (scene meshes as npz, A as a zarr group) and read
    back whole."""
    from objcam.scene import use_mitsuba
    from objcam.transport.build import BuildSettings, build_camera
    from objcam.transport.geometry import SceneGeometry
    from objcam.transport.storage import load_group

    use_mitsuba()
    with tempfile.TemporaryDirectory(prefix="objcam-design-") as tmp:
        root = Path(tmp)
        mesh.save(root / "object.npz")
        make_plane(p.plane_size).save(root / "support.npz")
        desc = SceneDescription(object_mesh="object.npz", support_mesh="support.npz", support_is_plane=True,
                                albedo_object=AlbedoValue(rgb=(p.object_albedo,) * 3),
                                albedo_support=AlbedoValue(rgb=(p.support_albedo,) * 3))
        geo = SceneGeometry.load(desc, root, env_height=p.env_height)
        settings = BuildSettings(model="direct", env_height=p.env_height, samples=p.samples,
                                 subpixel_samples=p.subpixel_samples, seed=p.seed, use_valid=False)
        metrics = build_camera(geo, camera, root / "A", settings)
        tr = load_group(root / "A")
    return tr, metrics
