"""Export: fitted networks -> ONNX files, generated GLSL, and the scene manifest.

Filled in by the training/export stage; nothing here yet imports torch at module level.
"""

__all__: list[str] = []
