"""Capture front end: the building blocks of the ``ingest`` stage.

- :mod:`objcam.capture.raw`: raws / 16-bit TIFFs -> linear camera RGB in white-level units + saturation mask;
  JPEG/PNG views as 8-bit.
- :mod:`objcam.capture.exif`: exposure time, ISO, f-number, camera from EXIF (exifread, OpenImageIO fallback).
- :mod:`objcam.capture.hdr`: exposure-bracket merges (raw-linear, and JPEG via a Debevec response).
- :mod:`objcam.capture.dng`: synthetic Bayer DNGs (PiDNG) with camera-like metadata and a sensor noise model.
- :mod:`objcam.capture.photos`: a capture's folders -> per-second linear images (list, decode, merge a folder's
  bracket, resize, undistort), what the ``ingest`` stage runs.
"""

from objcam.capture.exif import ExposureInfo, exposure_time, read_exif
from objcam.capture.hdr import MergeResult, apply_response, merge_frames, merge_ldr_bracket, merge_raw_bracket
from objcam.capture.raw import LinearImage, read_ldr, read_linear, read_raw, read_tiff16

__all__ = ["ExposureInfo", "LinearImage", "MergeResult", "apply_response", "exposure_time", "merge_frames",
           "merge_ldr_bracket", "merge_raw_bracket", "read_exif", "read_ldr", "read_linear", "read_raw",
           "read_tiff16"]
