"""Diagnostics of the light-transport system (the method's Section 5): which pixels the solve leans on, how well
each texel is determined, and how many envmap modes the shadows resolve.

Per colour channel, with ``A`` (M, N) pixels x kept texels and ``lr`` the *absolute* ridge weight
(:func:`absolute_ridge` converts objcam's relative weights, multiples of ``mean(diag(A^T A))``):

- :mod:`.leverage`: :func:`ridge_cholesky` (factor ``A^T A + lr I`` once and share it), :func:`leverage` (M,),
  :func:`cooks_distance` (M,) or (M, C);
- :mod:`.uncertainty`: :func:`texel_uncertainty` (N,), :func:`inverse_diagonal` (N,), :func:`gain_images` (k, M),
  :func:`regularizer`, :func:`to_grid` / :func:`scatter_to_image` / :func:`texel_columns` (back to envmap /
  image layout);
- :mod:`.spectrum`: :func:`singular_spectrum` (min(M, N),), :func:`effective_rank`,
  :func:`entropy_effective_rank`, :func:`ridge_dof`;
- :mod:`.plots`: PNGs for a report (:func:`plot_spectrum`, :func:`plot_envmap_map`, :func:`plot_image_map`,
  :func:`plot_image_grid`).

All dense linear algebra runs under :func:`objcam.threads.single_blas_thread` (:func:`inverse_diagonal`: as many
BLAS threads as it is given).
"""

from objcam.analysis.leverage import (
    absolute_ridge,
    cholesky_factor,
    column_scale,
    cooks_distance,
    leverage,
    predict,
    ridge_cholesky,
)
from objcam.analysis.plots import plot_envmap_map, plot_image_grid, plot_image_map, plot_spectrum
from objcam.analysis.spectrum import (
    DEFAULT_RANK_TOL,
    effective_rank,
    entropy_effective_rank,
    ridge_dof,
    singular_spectrum,
)
from objcam.analysis.uncertainty import (
    gain_images,
    inverse_diagonal,
    regularizer,
    scatter_to_image,
    texel_columns,
    texel_uncertainty,
    to_grid,
)

__all__ = [
    "DEFAULT_RANK_TOL",
    "absolute_ridge",
    "cholesky_factor",
    "column_scale",
    "cooks_distance",
    "effective_rank",
    "entropy_effective_rank",
    "gain_images",
    "inverse_diagonal",
    "leverage",
    "plot_envmap_map",
    "plot_image_grid",
    "plot_image_map",
    "plot_spectrum",
    "predict",
    "regularizer",
    "ridge_cholesky",
    "ridge_dof",
    "scatter_to_image",
    "singular_spectrum",
    "texel_columns",
    "texel_uncertainty",
    "to_grid",
]
