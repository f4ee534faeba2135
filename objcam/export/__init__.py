"""``objcam export CAPTURE OUT``: what objcam recovered, in the formats other tools open.

- :mod:`objcam.export.envmaps`: the envmaps as EXR and Radiance .hdr (standard lat-long convention), optionally
  upsampled for display, and the box bitmap Mitsuba needs to emit box texels;
- :mod:`objcam.export.meshes`: object and support as PLY, OBJ + MTL with UVs and the albedo texture, binary glTF;
- :mod:`objcam.export.cameras`: the cameras as a COLMAP text model and a nerfstudio ``transforms.json``;
- :mod:`objcam.export.mitsuba_xml`: one Mitsuba 3 scene per target that renders the solve's prediction;
- :mod:`objcam.export.blender`: a Blender Python script that builds the world, the objects and the cameras;
- :mod:`objcam.export.run`: reads a finished work folder and writes all of it (``export.json`` lists the files).
"""
