"""objcam.geometry: the scene's meshes and first albedo from photogrammetry (issue 4).

Small modules with one job each: ``views`` (load ingest + sfm artifacts), ``plane`` (robust support-plane fit),
``silhouette`` (object masks from plane-induced parallax), ``maskfield`` (a mask's signed distance image),
``outline`` (where a mask's edge lies off the image's edge), ``ambiguity`` (background pixels the object explains
as well), ``carve`` (coarse-to-fine silhouette carving into a signed field), ``hull`` (the two-pass visual hull),
``surface`` (surface nets on that field, pymeshlab cleaning), ``meshcheck`` (a known mesh's bad-input checks),
``register`` (known-shape registration to the hull), ``silfit`` (its refinement against the silhouettes),
``chamfer`` (distances between meshes), ``uv`` (xatlas), ``raster`` (texel -> surface point),
``bake`` (albedo from the linear views). Synthetic ingest/sfm-contract inputs rendered for tests and bench are
made by :mod:`objcam.synth.geometry_inputs`.
"""
