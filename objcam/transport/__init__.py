"""Light transport: the matrix A of y = A x (pixels of a target photo from envmap texels).

Stage entry: objcam.stages.transport. For consumers: :func:`load_transport` and :class:`Transport`
(objcam.transport.storage), :func:`pool_target` (objcam.transport.pixels).
"""

from objcam.transport.pixels import pool_target
from objcam.transport.storage import Transport, load_transport

__all__ = ["Transport", "load_transport", "pool_target"]
