"""Synthetic captures: everything objcam renders to stand in for photographs, with the truth to score against.

- :mod:`objcam.synth.capture`: known-geometry captures (``objcam synth OUT``): :class:`SynthParams`,
  :func:`synthesize`; the object on a plane under an envmap, path-traced targets with camera noise, ``truth/``.
- :mod:`objcam.synth.full`: photographed captures (``objcam synth OUT --full``): :class:`FullSynthParams`,
  :func:`synthesize_full`; raw DNG views, bracketed targets and a chrome ball on the printed board.
- :mod:`objcam.synth.views`: the photogrammetry ring of views of the object on the printed board
  (:class:`ViewRingParams`, :func:`ring_cameras`, :func:`board_scene`, :func:`render_views`).
- :mod:`objcam.synth.geometry_inputs`: the geometry and texture stages' inputs (capture, ``ingest`` and ``sfm``
  artifacts) rendered from that ring, and the texture's albedo error against their truth.
- :mod:`objcam.synth.probe`: chrome-ball renders and exposure brackets, written in the ingest stage's contract.
- :mod:`objcam.synth.split_render`: the low-variance renderer of the ``split`` estimator (stratified direct
  light plus path-traced indirect).
- :mod:`objcam.synth.assets`: the bundled envmaps and object meshes, loaded and scaled; the PLY writer.
- :mod:`objcam.synth.noise`: the camera noise model (shot and read noise, clipping, auto exposure) and the
  Monte Carlo noise of a render.

Nothing is re-exported here: import from the submodules (they import each other directly, never through this
package), so importing one does not pull in the others' dependencies.
"""
