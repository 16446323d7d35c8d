"""Deformable objects (``prt-train --deform``).

- :mod:`.deform_sources`  rest pose + frames: OBJ/PLY folders, glTF clips, built-in deformers
- :mod:`.gltf_animation`  a glTF 2.0 reader and poser (skinning, morph targets)
- :mod:`.deform_build`    shape code, per-frame samples and transfer, shape-conditioned networks
"""
