"""objcam: turn an ordinary object into a camera.

Photograph an object and its cast shadows; objcam renders the scene's light-transport matrix and solves for the
environment map seen from the object (and, with several targets, the albedo of the surface it stands on).
"""

__version__ = "0.1.0"
