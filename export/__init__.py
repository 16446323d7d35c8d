"""prt.export: fitted networks -> the files of a scene folder.  Imports runtime, never train.

- :mod:`prt.export.scene`       a whole built scene: segment files, geometry, ``scene.json``
- :mod:`prt.export.onnx_model`  segment networks as ONNX files, from plain arrays
- :mod:`prt.export.glsl`        GLSL generated from an ONNX segment network
- :mod:`prt.export.manifest`    writing ``scene.json`` (validated, atomic, byte-stable)
- :mod:`prt.export.precision`   reduced-precision variants of the ONNX networks (fp16, int8)
- :mod:`prt.export.web`         ``prt-web``: a built scene as a static WebGL2 page (``web_assets``: its data)
"""

__all__: list[str] = []
