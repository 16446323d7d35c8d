"""Light transport at the samples: ray-traced transfer, the precompute stage, interreflection.

- :mod:`.transfer`          ray-traced SH transfer (Embree; sphere tracing for SDFs)
- :mod:`.precompute`        samples -> transfer -> segments, chunked and resumable
- :mod:`.interreflection`   the bounce operator and the build's bounce stage
- :mod:`.bounce_depth`      how many bounces a scene needs (``--bounces auto``)
- :mod:`.transfer_texture`  baking transfer textures (``--transfer-texture``)
- :mod:`.preview`           ``preview.png`` of the precomputed samples
"""
