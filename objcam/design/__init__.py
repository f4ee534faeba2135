"""Occluder design (``objcam design``): which object makes the better camera, before any capture.

Every occluder (the bundled bunny, a sphere, a coded-aperture mask held above the plane, any user mesh) is put
on one shared setup -- the plane z = 0, one camera, one envmap grid, comparable size -- and its direct-light
transport A is built with the transport stage's code. Each is then scored with the analysis stage's
diagnostics: per-texel uncertainty sqrt(diag((A^T A + lr I)^-1)) with one absolute ridge weight for all, pixel
leverage, effective rank.

Modules, one job each: :mod:`.params` (DesignParams), :mod:`.occluders` (the meshes), :mod:`.scene` (camera,
reference scale, A), :mod:`.scoring` (maps and numbers), :mod:`.figures` (PNGs), :mod:`.page` (HTML),
:mod:`.run` (the OUT folder), :mod:`.cli` (the command's options and table).
"""

from objcam.design.params import DesignParams
from objcam.design.run import DesignResult, run_design

__all__ = ["DesignParams", "DesignResult", "run_design"]
