"""The capture front end: camera poses and intrinsics from photos of the object standing on a printed ChArUco board.

- ``board``: the board (white centre, markers in the outer ring), its albedo texture, world points, detection.
- ``colmap``: SfM with pycolmap (views and targets together; optionally started from board poses).
- ``align``: board corners -> the similarity SfM -> world (metres, z up, board plane z = 0); PnP cross-check;
  intrinsics from the board.
- ``bundle``: final bundle adjustment with the board held fixed.
- ``report``: green / yellow / red checks with fixes.
- ``frontend``: all of it: :func:`objcam.sfm.frontend.estimate_cameras`.

Its accuracy benchmark lives outside the package, in bench/sfm_bench.py (``python -m bench.sfm_bench OUT``).

Submodules import OpenCV / pycolmap / scipy lazily where they can; import what you need from them directly.
"""
