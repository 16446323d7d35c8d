"""What a build starts from: geometry (meshes, SDF scenes, mixed scenes), materials, UVs, samples.

- :mod:`.geometry`   a mesh or SDF scene, cleaned, oriented, normalised into [-1, 1]^3
- :mod:`.objfile`    a tolerant Wavefront OBJ reader
- :mod:`.mixed`      mixed scenes: meshes, analytic and neural SDFs composed into one geometry
- :mod:`.materials`  per-object materials (OBJ/MTL, glTF); :mod:`.albedo_uv` the mesh's own UVs
- :mod:`.uv_atlas`   UVs for transfer textures (the mesh's own, or xatlas)
- :mod:`.sampling`   area-uniform surface samples; :mod:`.adaptive` a second pass where transfer varies
"""
