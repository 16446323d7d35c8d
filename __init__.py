"""prt: precomputed radiance transfer learnt by small neural networks.

Subpackages (the layering runs one way: train -> export -> runtime):

- :mod:`prt.train`   geometry sources, surface samples, ray-traced ground-truth transfer,
                     segments, (later) network fitting.  May use torch.
- :mod:`prt.export`  networks -> ONNX files, generated GLSL, scene manifest.
- :mod:`prt.runtime` spherical harmonics, scene loading, rendering backends.  Never torch.
- :mod:`prt.shaders` GLSL sources and templates (package data).
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
