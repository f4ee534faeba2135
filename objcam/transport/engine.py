"""Where A's column blocks are computed: in this process (the default, :class:`InProcess`), or as shards on a Dask
cluster (:class:`objcam.transport.shards.DaskEngine`, installed by ``objcam run --cluster``).

An engine does the three parts of a build that scale with the columns: the direct-light column blocks, the
indirect light added to every column chunk (model ``auto`` with the gather), and the Gram matrix. Every column
depends only on its texel, the model's state and the seed (the shadow rays are hashed per pixel, texel and seed),
never on which process computed it or on its neighbours in a block, so every engine writes the same A.
This module imports nothing of Dask: the default path never loads it.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np


class InProcess:
    """Every block in this process, one after another (the columns' kernels use every core through Dr.Jit)."""

    name = "in-process"

    def direct_columns(self, dm, blocks: list[np.ndarray], folder: Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(texels (B,), columns (C, M, B) float32) of each block of ``blocks`` (contiguous texel ranges), in
        order. dm: a DirectModel or SplitDirect; folder: the camera's zarr group (unused here)."""
        for tex in blocks:
            yield tex, dm.columns(tex)

    def add_indirect(self, folder: Path, gi) -> None:
        """A[:, :, a:b] += gi.columns(a, b) over A's column chunks (gi: objcam.transport.gather.GatherIndirect)."""
        from objcam.transport.storage import add_to_columns

        add_to_columns(folder, lambda a, b: gi.columns(a, b))

    def write_gram(self, folder: Path) -> float:
        """gram.npy beside A; returns the seconds it took."""
        from objcam.transport.storage import write_gram

        return write_gram(folder)

    def metrics(self) -> dict:
        return {"engine": self.name}


_current: list = [InProcess()]


def current():
    """The engine the transport stage uses now."""
    return _current[-1]


@contextmanager
def using(engine):
    """Make ``engine`` the current one inside the block."""
    _current.append(engine)
    try:
        yield engine
    finally:
        _current.pop()
