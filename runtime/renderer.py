"""The embedding API: :class:`Scene` and :class:`Renderer`.

A frame runs three stages, each timed (milliseconds in :attr:`Renderer.timings`):

1. G-buffer (``gbuffer``): position, normal, segment id per pixel (rasterised or sphere traced).
2. Transfer, by the backend chosen by name (:mod:`prt.runtime.backends`; its stages timed as
   it names them):
   - ``"onnx"`` (the analogue of the paper's CUDA path): read the G-buffer back (``readback``),
     pack covered fragments by segment (``pack``), run each segment's ONNX model on its batch
     (``inference``), gather the results per covered pixel (``scatter``);
   - ``"glsl"``: a full-screen pass evaluates each fragment's network in the fragment shader
     (``network``), from GLSL generated out of the ONNX weights.
3. Shading (``shade``), one definition with two twins tested against each other: a transfer
   that a backend returns on the CPU (:class:`prt.runtime.backends.CpuTransfer`) is shaded
   there with :func:`prt.runtime.shading.shade` (numpy); one it leaves on the GPU is shaded by
   a full-screen pass with ``shading.glsl``.  Then the image is assembled (``readout``).

Transfer depends only on the geometry and the camera: when only the light, the material or
the backend's shading inputs change, :meth:`Renderer.render` re-shades the cached transfer and
runs no network (``stats["network_runs"]`` does not move).
"""

from __future__ import annotations

import functools
import time
from importlib import resources
from pathlib import Path

import moderngl
import numpy as np

from ..shaders import assemble
from .backends import BACKENDS, CpuTransfer, TransferBackend, create_backend
from .camera import DEFAULT_CAMERA, Camera
from .envmap import load_envmap_sh
from .envmaps import BUNDLED_ENVMAPS, DEFAULT_ENVMAP, bundled_envmap_path
from .errors import InputError
from .gbuffer import GBufferPass
from .gl import ShaderCompileError, bind_framebuffer, compile_program, create_context, draw_fullscreen
from .manifest import Manifest, load_manifest
from .shading import GLSL_DEFINES, GLSL_FILES, Lighting, Material, shade, shader_uniforms, to_srgb8

__all__ = ["Scene", "Renderer", "BACKENDS", "demo_scene_path", "ShaderCompileError"]


def demo_scene_path() -> Path:
    """The bundled demo scene (Spot, public domain, small networks)."""
    return Path(str(resources.files(__package__).joinpath("data", "demo", "scene.json")))


class Scene:
    """A loaded, validated scene manifest.

    ``Scene.load(path)`` accepts a ``scene.json`` or its folder; ``Scene.load()`` opens the
    bundled demo scene.
    """

    def __init__(self, manifest: Manifest):
        self.manifest = manifest

    @classmethod
    def load(cls, path=None) -> "Scene":
        return cls(load_manifest(demo_scene_path() if path is None else path))

    @property
    def name(self) -> str:
        return self.manifest.name

    @property
    def path(self) -> Path:
        return self.manifest.path

    @property
    def network_segments(self) -> list:
        return [s for s in self.manifest.segments if s.kind == "network"]

    def __repr__(self) -> str:
        m = self.manifest
        return f"Scene({m.name!r}, {m.geometry.type}, {len(m.segments)} segments, {len(self.network_segments)} networks)"


class Renderer:
    """Renders a :class:`Scene` headlessly (or into a window's context).

    Parameters
    ----------
    scene : Scene
    width, height : image size in pixels
    backend : a name in :data:`prt.runtime.backends.BACKENDS` (``"onnx"``, ``"glsl"``)
    providers : ONNX Runtime execution providers (default: CUDA where present, else CPU)
    threads : CPU threads for the ONNX backend (default: all cores)
    ctx : an existing moderngl context (e.g. a window's); default: a headless EGL context
    """

    def __init__(self, scene: Scene, width: int = 512, height: int = 512, backend: str = BACKENDS[0], *,
                 providers=None, threads: int | None = None, ctx: moderngl.Context | None = None):
        if backend not in BACKENDS:
            raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if width < 1 or height < 1:
            raise InputError(f"image size must be positive, got {width}x{height}")
        self.scene = scene
        self.width, self.height = int(width), int(height)
        self._own_ctx = ctx is None
        self.ctx = ctx if ctx is not None else create_context()
        self._bound_fbo = self.ctx.fbo  # bound again on close: a released framebuffer must not stay bound
        m = scene.manifest
        if m.sh_bands != 4:
            raise InputError(f"{m.path}: the renderer's shaders handle 4 SH bands, the scene has {m.sh_bands}")
        self.gbuffer = GBufferPass(self.ctx, m, self.width, self.height)
        self._backend_options = {"providers": providers, "threads": threads}
        self._backends: dict[str, TransferBackend] = {}  # created on first use, kept while switching
        size = (self.width, self.height)
        self._t_textures = [self._float_texture(size) for _ in range(4)]
        self._t_fbo = self.ctx.framebuffer(self._t_textures)
        self._out_texture = self._float_texture(size)
        self._out_fbo = self.ctx.framebuffer([self._out_texture])
        self._image = np.empty((self.height, self.width, 4), dtype=np.float32)
        shade_source = assemble(*GLSL_FILES, "shade_pass.frag", defines=GLSL_DEFINES)
        self._shade_program = compile_program(self.ctx, shade_source, "shade_pass.frag")
        self._vao = self.ctx.vertex_array(self._shade_program, [])
        # A transfer on the CPU: covered pixels, their transfer, and the image being assembled
        self._covered = np.zeros(0, dtype=np.int64)
        self._transfer_cov = np.zeros((0, 16), dtype=np.float32)
        self._geometry_cov: tuple[np.ndarray, np.ndarray] | None = None
        self._packed: np.ndarray | None = None
        self._cpu_image = np.zeros((self.height * self.width, 3), dtype=np.float32)

        self.camera = Camera.from_manifest(m.camera)
        self._envmap_sh: dict[str, np.ndarray] = {}
        lighting = m.lighting
        if lighting.envmap is not None:
            self.lighting = Lighting.from_envmap(lighting.envmap, rotation=lighting.rotation)
        elif lighting.sh is not None:
            self.lighting = Lighting.from_sh(lighting.sh, rotation=lighting.rotation)
        else:
            self.lighting = Lighting.from_envmap(bundled_envmap_path(DEFAULT_ENVMAP))
        mat = m.material
        self.material = Material(kind=mat.type, **{k: getattr(mat, k) for k in ("albedo", "specular", "exponent") if getattr(mat, k) is not None})
        self.backend = backend
        self.timings: dict[str, float] = {}
        self.stats = {"frames": 0, "network_runs": 0, "relight_frames": 0}
        self._transfer_valid = False
        self._transfer_on_cpu = True

    # ------------------------------------------------------------------ settings

    def set_camera(self, eye=DEFAULT_CAMERA["eye"], target=DEFAULT_CAMERA["target"], up=DEFAULT_CAMERA["up"],
                   fov: float = DEFAULT_CAMERA["fov"]) -> None:
        """Place the camera (scene units; ``fov`` is the vertical field of view in degrees)."""
        try:
            self.camera = Camera(eye=eye, target=target, up=up, fov_y=fov)
        except ValueError as exc:
            raise InputError(f"camera: {exc}") from None
        self._transfer_valid = False

    def set_camera_object(self, camera: Camera) -> None:
        self.camera = camera
        self._transfer_valid = False

    def set_envmap(self, envmap, rotation=None) -> None:
        """Light with an equirectangular ``.hdr``/``.exr`` file, or a bundled map by name
        (:data:`prt.runtime.envmaps.BUNDLED_ENVMAPS`); ``rotation`` is a 3x3 matrix."""
        path = bundled_envmap_path(envmap) if isinstance(envmap, str) and envmap in BUNDLED_ENVMAPS else envmap
        key = str(Path(path).resolve()) if Path(path).exists() else str(path)
        if key not in self._envmap_sh:  # turning the light must not re-read and re-project the file
            self._envmap_sh[key] = load_envmap_sh(path, self.scene.manifest.sh_bands)
        self.lighting = Lighting.from_sh(self._envmap_sh[key], rotation=rotation)

    def set_lighting_sh(self, coeffs, rotation=None) -> None:
        """Light with SH coefficients (16, 3)."""
        self.lighting = Lighting.from_sh(coeffs, rotation=rotation)

    def set_material(self, kind: str = "diffuse", **params) -> None:
        """``"diffuse"`` (albedo) or ``"glossy"`` (albedo, specular, exponent)."""
        try:
            self.material = Material(kind=kind, **params)
        except TypeError as exc:
            raise InputError(f"material: {exc}") from None

    def set_backend(self, backend: str) -> None:
        if backend not in BACKENDS:
            raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if backend != self.backend:
            self.backend = backend
            self._transfer_valid = False

    # ------------------------------------------------------------------ frames

    def render(self) -> np.ndarray:
        """One frame: (H, W, 3) float32 linear radiance, row 0 at the top, background 0."""
        timings: dict[str, float] = {}
        t_frame = time.perf_counter()
        if not self._transfer_valid:
            self._compute_transfer(timings)
            self.stats["network_runs"] += 1
        else:
            self.stats["relight_frames"] += 1
        t0 = time.perf_counter()
        if self._transfer_on_cpu:
            radiance = self._shade_cpu()
            t1 = time.perf_counter()
            self._cpu_image[self._covered] = radiance
            image = self._cpu_image.reshape(self.height, self.width, 3).copy()
        else:
            self._shade_gl()
            self.ctx.finish()
            t1 = time.perf_counter()
            self._out_fbo.read_into(self._image, components=4, dtype="f4")
            image = np.ascontiguousarray(self._image[::-1, :, :3])
        t2 = time.perf_counter()
        timings["shade"] = 1e3 * (t1 - t0)
        timings["readout"] = 1e3 * (t2 - t1)
        timings["frame"] = 1e3 * (t2 - t_frame)
        self.timings = timings
        self.stats["frames"] += 1
        return image

    def render_srgb(self, exposure: float = 1.0) -> np.ndarray:
        """One frame tone-mapped for display: (H, W, 3) uint8 sRGB."""
        return to_srgb8(self.render(), exposure)

    def render_transfer(self) -> np.ndarray:
        """The transfer image of the current view: (H, W, 16) float32, row 0 at the top."""
        if not self._transfer_valid:
            self._compute_transfer({})
            self.stats["network_runs"] += 1
        if self._transfer_on_cpu:
            full = np.zeros((self.height * self.width, 16), dtype=np.float32)
            full[self._covered] = self._transfer_cov
            return full.reshape(self.height, self.width, 16)
        parts = []
        for tex in self._t_textures:
            a = np.frombuffer(tex.read(), dtype=np.float32).reshape(self.height, self.width, 4)
            parts.append(a[::-1])
        return np.concatenate(parts, axis=2)

    def gbuffer_image(self):
        """The G-buffer of the current view (see :class:`prt.runtime.gbuffer.GBuffer`)."""
        self.gbuffer.render(self.camera)
        return self.gbuffer.read()

    # ------------------------------------------------------------------ stages

    def _compute_transfer(self, timings: dict) -> None:
        t0 = time.perf_counter()
        self.gbuffer.render(self.camera)
        self.ctx.finish()
        t1 = time.perf_counter()
        backend = self._backend()
        result = backend.run(self.gbuffer, self._t_fbo)
        timings.update({"gbuffer": 1e3 * (t1 - t0), **backend.timings})
        if result is not None:
            self._take_cpu_transfer(result)
        self._transfer_on_cpu = result is not None
        self._transfer_valid = True

    def _take_cpu_transfer(self, result: CpuTransfer) -> None:
        self._cpu_image[self._covered] = 0.0  # the previous view's pixels
        self._covered, self._transfer_cov = result.covered, result.transfer
        self._packed, self._geometry_cov = result.packed, None

    def _shade_cpu(self) -> np.ndarray:
        """Radiance of the covered pixels (M, 3) from the cached transfer (numpy twin of the shader)."""
        # BLAS worker threads spinning after these small products steal the cores from ONNX
        # Runtime's threads in the next frame; one thread is as fast for them.
        with _blas_controller().limit(limits=1, user_api="blas"):
            return self._shade_cpu_products()

    def _shade_cpu_products(self) -> np.ndarray:
        if self.material.kind == "diffuse":  # the common case, in float32: T @ (albedo * L)
            light = (self.lighting.sh * np.asarray(self.material.albedo)).astype(np.float32)
            return np.maximum(self._transfer_cov @ light, 0.0)
        if self._geometry_cov is None:
            rows = self._packed[self._covered]
            self._geometry_cov = (rows[:, 4:7], self.camera.eye[None, :] - rows[:, 0:3])
        normals, view_dirs = self._geometry_cov
        return shade(self._transfer_cov, normals, view_dirs, self.lighting, self.material)

    def _shade_gl(self) -> None:
        program = self._shade_program
        for name, value in shader_uniforms(self.lighting, self.material).items():
            if name in program:
                program[name].write(np.ascontiguousarray(value).tobytes())
        program["u_eye"].value = tuple(float(v) for v in self.camera.eye)
        textures = [(self.gbuffer.position_texture, 0), (self.gbuffer.normal_texture, 1)]
        for k, tex in enumerate(self._t_textures):
            textures.append((tex, 2 + k))
            program[f"u_t{k}"].value = 2 + k
        program["u_position"].value = 0
        program["u_normal"].value = 1
        draw_fullscreen(self.ctx, self._out_fbo, self._vao, textures)

    def _backend(self) -> TransferBackend:
        if self.backend not in self._backends:
            self._backends[self.backend] = create_backend(self.backend, self.ctx, self.scene.manifest, **self._backend_options)
        return self._backends[self.backend]

    @property
    def network_calls(self) -> int:
        """How often a network stage ran (both backends)."""
        return self.stats["network_runs"]

    # ------------------------------------------------------------------ plumbing

    def _float_texture(self, size):
        tex = self.ctx.texture(size, 4, dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return tex

    def close(self) -> None:
        """Release GPU resources and ONNX sessions (also on ``with`` exit)."""
        for backend in self._backends.values():
            backend.release()
        self._backends.clear()
        self.gbuffer.release()
        bind_framebuffer(self.ctx, self._bound_fbo)
        for obj in [*self._t_textures, self._t_fbo, self._out_texture, self._out_fbo, self._vao, self._shade_program]:
            obj.release()
        if self._own_ctx:
            self.ctx.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@functools.lru_cache(maxsize=1)
def _blas_controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()
