"""objcam.geometry: the scene's meshes and first albedo from photogrammetry (issue 4).

Small modules with one job each: ``views`` (load ingest + sfm artifacts), ``plane`` (robust support-plane fit),
``silhouette`` (object masks from plane-induced parallax), ``carve`` (coarse-to-fine silhouette carving into a
signed field), ``surface`` (surface nets on that field, pymeshlab cleaning), ``register`` (known-shape
registration), ``chamfer`` (distances between meshes), ``uv`` (xatlas), ``raster`` (texel -> surface point),
``bake`` (albedo from the linear views), ``synthetic`` (ingest/sfm-contract inputs rendered for tests and bench).
"""
