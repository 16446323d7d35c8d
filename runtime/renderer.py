"""The embedding API: :class:`Scene` and :class:`Renderer`.

A frame runs three stages, each timed (milliseconds in :attr:`Renderer.timings`):

1. G-buffer (``gbuffer``): position, normal, segment id per pixel (rasterised or sphere traced);
   for a frame shaded on the CPU the env-map background's pass is drawn with it (read back later,
   ``background``: the read-back and copy).
2. Transfer, by the backend chosen by name (:mod:`prt.runtime.backends`; its stages timed as
   it names them):
   - ``"onnx"`` (the analogue of the paper's CUDA path): read the G-buffer back (``readback``),
     pack covered fragments by segment with a counting sort (``pack``), run each segment's ONNX
     model on its batch (``inference``); the transfer stays in packed order;
   - ``"glsl"``: a full-screen pass evaluates each fragment's network in the fragment shader
     (``network``), from GLSL generated out of the ONNX weights.
3. Shading (``shade``), one definition with two twins tested against each other: a transfer
   that a backend returns on the CPU (:class:`prt.runtime.backends.CpuTransfer`) is shaded
   there with :func:`prt.runtime.shading.shade` (numpy), packed row by row; one it leaves on the
   GPU is shaded by a full-screen pass with ``shading.glsl`` (the env-map background drawn
   into the same texture, ``background``).  A CPU frame is then assembled (``readout``: the
   shaded rows scattered once into the image).

``frame`` is the frame as its user sees it: drawn and finished where it is shaded (a GPU frame
in its texture, :meth:`Renderer.draw`).  Reading a GPU frame back to the CPU is done only when
pixels are asked for (:meth:`Renderer.render`) and timed apart (``frame_readback``); a frame
drawn and not read is checked for broken transfer by an occlusion query (``check``).
:attr:`Renderer.gl_renderer` names the device that drew it.

Transfer depends only on the geometry and the camera: when only the light, the material or
the backend's shading inputs change, :meth:`Renderer.render` re-shades the cached transfer and
runs no network (``stats["network_runs"]`` does not move).

A frame is never returned with holes: a transfer that is NaN or Inf after inference (either
backend), or an image that is, raises :class:`~prt.runtime.errors.FrameError` (one line).
"""

from __future__ import annotations

import functools
import os
import threading
import time
import weakref
from importlib import resources
from pathlib import Path

import moderngl
import numpy as np

from ..shaders import assemble
from .backends import ALL_BACKENDS, BACKENDS, CpuTransfer, TransferBackend, create_backend
from .backends.onnx import check_providers
from .background import EnvmapBackground
from .camera import DEFAULT_CAMERA, Camera, fit_near, scene_box
from . import exposure_gl
from .exposure import default_exposure, parse_exposure
from .envmap import load_envmap_sh
from .envmaps import BUNDLED_ENVMAPS, DEFAULT_ENVMAP, bundled_envmap_path
from .checks import count_nonfinite, positive_int
from .errors import ArgumentTypeError, FrameError, InputError, RendererStateError
from .deformation import Deformation
from .gbuffer import PACKED_SEGMENT, GBufferPass, load_mesh
from .gl import ShaderCompileError, bind_framebuffer, compile_program, create_context, draw_fullscreen, FlagCounter
from .manifest import Manifest, load_manifest
from .interpolation import check_tolerance
from .resources import RendererResources, make_current
from .segmentation import scatter_rows
from .albedo_textures import AlbedoTextures
from .materials import MaterialTable, load_albedo_textures, object_materials, shade_objects
from .shading import GLSL_DEFINES, GLSL_FILES, Lighting, Material, diffuse_light_matrix, shade, shader_uniforms, to_srgb8

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
        if not isinstance(manifest, Manifest):
            hint = f"; open a file with Scene.load({str(manifest)!r})" if isinstance(manifest, (str, os.PathLike)) else ""
            raise ArgumentTypeError(f"Scene: expected a Manifest, got {type(manifest).__name__}{hint}")
        self.manifest = manifest
        self.deformation: Deformation | None = None  # deformable scenes: frames, codes, basis
        if manifest.deformation is not None:
            self.deformation = Deformation.load(manifest.deformation.path, load_mesh(manifest.geometry.path)["vertices"].shape[0])

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


def _in_context(method):
    """Run a Renderer method with its GL context made current first: several renderers in one
    thread, each with its own context or a shared one, each draw into theirs; the last one used
    stays current, as a single renderer's always was."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        if not self._closed:
            make_current(self.ctx)
        return method(self, *args, **kwargs)

    return wrapper


class Renderer:
    """Renders a :class:`Scene` headlessly (or into a window's context).

    Parameters
    ----------
    scene : Scene
    width, height : image size in pixels
    backend : a name in :data:`prt.runtime.backends.ALL_BACKENDS` (``"onnx"``, ``"glsl"``; ``"texture"``
        for a scene with a transfer texture)
    providers : ONNX Runtime execution providers, full or short names (``["cuda", "cpu"]``; default: the
        environment variable ``PRT_ONNX_PROVIDERS``, else CUDA where present, then CPU); one missing here
        (CUDA without a GPU build of onnxruntime) is an InputError
    threads : CPU threads for the ONNX backend (default: all cores)
    ctx : an existing moderngl context (e.g. a window's); default: a headless EGL context on ``gl_device``
    gl_device : the EGL device of the headless context: ``"auto"`` (the GPU where there is one, else
        llvmpipe), an index or a name matched against GL_RENDERER (default: the environment variable
        ``PRT_GL_DEVICE``, else auto; :mod:`prt.runtime.gl_devices`); :attr:`gl_renderer` says which drew
    interpolate : relative transfer tolerance of screen-space interpolation for the ONNX backend (e.g. 0.05;
        :mod:`prt.runtime.interpolation`): the networks run on every fourth pixel of every fourth row
        and where interpolating from neighbours is unsafe, the rest is interpolated.  None (the
        default) or 0: every covered pixel runs its network.
    exposure : ``"auto"`` (:mod:`prt.runtime.exposure`) or a number, what :meth:`render_srgb` uses (default:
        :func:`~prt.runtime.exposure.default_exposure`, "auto" for a scene, 1 for an object); :meth:`set_exposure`

    Notes
    -----
    Every argument is checked: a wrong type raises :class:`~prt.runtime.errors.ArgumentTypeError`,
    a wrong value (a size the GL driver cannot allocate, ``threads < 1``) an
    :class:`~prt.runtime.errors.InputError`, each one line.

    Threading contract
    ------------------
    A Renderer, like the OpenGL context it draws with, belongs to the thread that created it:
    a call from any other thread raises :class:`~prt.runtime.errors.RendererStateError` (it
    would otherwise render another thread's camera, or draw with a context that is not
    current there).  To render from several threads, give each thread its own Renderer.

    Lifetime
    --------
    :meth:`close` (or leaving a ``with`` block) releases the GL objects, the ONNX sessions and
    an own context at once; a Renderer that is never closed releases them when it is garbage
    collected.  Any call after :meth:`close` raises :class:`RendererStateError`.
    """

    def __init__(self, scene: Scene, width: int = 512, height: int = 512, backend: str = BACKENDS[0], *,
                 providers=None, threads: int | None = None, ctx: moderngl.Context | None = None,
                 interpolate: float | None = None, gl_device: str | int | None = None, exposure=None):
        self._owner = threading.get_ident()
        self._closed = True  # until the resources exist
        if not isinstance(scene, Scene):
            raise ArgumentTypeError(f"Renderer: scene must be a Scene (Scene.load(path)), got {type(scene).__name__}")
        width, height = positive_int(width, "Renderer: width"), positive_int(height, "Renderer: height")
        _check_backend(backend)
        if threads is not None:
            threads = positive_int(threads, "Renderer: threads (CPU threads of the ONNX backend)")
        providers = check_providers(providers, "Renderer: providers")
        interpolate = check_tolerance(interpolate, "Renderer: interpolate")
        if ctx is not None and not isinstance(ctx, moderngl.Context):
            raise ArgumentTypeError(f"Renderer: ctx must be a moderngl.Context, got {type(ctx).__name__}")
        if ctx is not None and gl_device is not None:
            raise InputError("Renderer: give ctx or gl_device, not both (the context's device is its own)")
        m = scene.manifest
        if m.sh_bands != 4:
            raise InputError(f"{m.path}: the renderer's shaders handle 4 SH bands, the scene has {m.sh_bands}")
        self.scene = scene
        self.width, self.height = width, height
        self._own_ctx = ctx is None
        self.ctx = ctx if ctx is not None else create_context(device=gl_device, origin="Renderer: gl_device")
        # What GC releases if close() is never called; it must not refer to self.
        self._resources = RendererResources(self.ctx, self._own_ctx, self.ctx.fbo)
        self._finalizer = weakref.finalize(self, self._resources.release, False)
        self._finalizer.atexit = False  # at exit the GL driver may be gone already
        self._bound_fbo = self.ctx.fbo  # bound again on close: a released framebuffer must not stay bound
        try:
            make_current(self.ctx)  # another renderer's context may be current
            _check_size(self.ctx, width, height)
            self._backend_options = {"providers": providers, "threads": threads, "interpolate": interpolate}
            self._backends = self._resources.backends  # created on first use, kept while switching
            self.gbuffer = self._resources.keep(GBufferPass(self.ctx, m, self.width, self.height))
            size = (self.width, self.height)
            # Transfer targets: 4 RGBA32F (16 coefficients), or 16 with interreflection (direct, indirect
            # R, G, B), then written as two framebuffers of 8 (GL 3.3's draw buffers; backends/glsl.py).
            self._transfer_width = m.transfer_width
            self._t_textures = [self._resources.keep(self._float_texture(size)) for _ in range(self._transfer_width // 4)]
            if len(self._t_textures) > 4:
                self._t_fbo = tuple(self._resources.keep(self.ctx.framebuffer(self._t_textures[k : k + 8])) for k in (0, 8))
            else:
                self._t_fbo = self._resources.keep(self.ctx.framebuffer(self._t_textures))
            self._out_texture = self._resources.keep(self._float_texture(size))
            self._out_fbo = self._resources.keep(self.ctx.framebuffer([self._out_texture]))
            _check_allocation(self.ctx, width, height)
            self._image = np.empty((self.height, self.width, 4), dtype=np.float32)
            shade_source = assemble(*GLSL_FILES, "shade_pass.frag", defines=self._shade_defines())
            self._shade_program = self._resources.keep(compile_program(self.ctx, shade_source, "shade_pass.frag"))
            self._vao = self._resources.keep(self.ctx.vertex_array(self._shade_program, []))
        except MemoryError:
            self._finalizer()
            raise InputError(f"image size {width}x{height}: not enough memory for the frame buffers") from None
        except BaseException:
            self._finalizer()
            raise
        # A transfer on the CPU: covered pixels, their transfer, and their position and normal
        self._covered = np.zeros(0, dtype=np.int64)
        self._transfer_cov = np.zeros((0, self._transfer_width), dtype=np.float32)
        self._geometry_cov: tuple[np.ndarray, np.ndarray] | None = None
        self._inputs: np.ndarray | None = None

        self.camera = fit_near(Camera.from_manifest(m.camera), scene_box(m))  # inside: a near plane for interiors
        self.exposure = default_exposure(m) if exposure is None else parse_exposure(exposure, "Renderer: exposure")
        self._envmap_sh: dict[str, np.ndarray] = {}
        lighting = m.lighting
        if lighting.envmap is not None:
            self.lighting = Lighting.from_envmap(lighting.envmap, rotation=lighting.rotation)
        elif lighting.sh is not None:
            self.lighting = Lighting.from_sh(lighting.sh, rotation=lighting.rotation)
        else:
            self.lighting = Lighting.from_envmap(bundled_envmap_path(DEFAULT_ENVMAP))
        # The env map drawn where no geometry is (set_background); it follows set_envmap.
        self._envmap_path = lighting.envmap if lighting.envmap is not None or lighting.sh is not None else bundled_envmap_path(DEFAULT_ENVMAP)
        self._envmap_rotation = lighting.rotation
        self.background = bool(lighting.background)
        self._background: EnvmapBackground | None = None
        self._gbuffer_generation = 0  # G-buffer renders so far: the background layer is redrawn on a new one
        self.background_with_gbuffer = True
        """A frame shaded on the CPU draws the background's pass right after the G-buffer's, one wait on the
        GL for both (False: when the frame is assembled, as before; ``studies/demo_fps.py`` compares them)."""
        mat = m.material
        self.material = Material(kind=mat.type, **{k: getattr(mat, k) for k in ("albedo", "specular", "exponent") if getattr(mat, k) is not None})
        # One material per object (runtime/materials.py); self.material is the scene-wide one.
        per_object = object_materials(m.raw, m.geometry.objects, str(m.path), root=m.root)
        self.materials = MaterialTable(m.geometry.objects or [], self.material, per_object, load_albedo_textures(per_object))
        self._object_ids_cov: np.ndarray | None = None
        self._uv_cov: np.ndarray | None = None
        self._material_gl: dict = {}  # the per-object shade program, its VAO and table texture
        self._flags: FlagCounter | None = None  # draw(): counts a GPU frame's broken-transfer marks
        self.backend = backend
        self.timings: dict[str, float] = {}
        # network_fraction: share of the last network frame's covered pixels that ran a network (screen-space interpolation: < 1)
        self.stats = {"frames": 0, "network_runs": 0, "relight_frames": 0, "network_fraction": 1.0}
        self._transfer_valid = False
        self._transfer_on_cpu = True
        self._closed = False
        self._code: np.ndarray | None = None  # deformable scenes: the pose's shape code
        self.pose: dict | None = None
        if scene.deformation is not None:
            self.set_deformation(frame=0)

    def _check_usable(self) -> None:
        """RendererStateError after close() or from a thread other than the creator (see the class docstring)."""
        if self._closed:
            raise RendererStateError("Renderer: used after close(); create a new Renderer")
        if threading.get_ident() != self._owner:
            raise RendererStateError(
                f"Renderer: called from thread {threading.current_thread().name!r}, but a Renderer belongs to the thread "
                "that created it; create one Renderer per thread"
            )

    # ------------------------------------------------------------------ settings

    def set_camera(self, eye=DEFAULT_CAMERA["eye"], target=DEFAULT_CAMERA["target"], up=DEFAULT_CAMERA["up"],
                   fov: float = DEFAULT_CAMERA["fov"]) -> None:
        """Place the camera (scene units; ``fov`` is the vertical field of view in degrees; an eye inside the
        scene's box gets the interior near plane, :func:`~prt.runtime.camera.fit_near`)."""
        self._check_usable()
        self.camera = fit_near(Camera(eye=eye, target=target, up=up, fov_y=fov), scene_box(self.scene.manifest))
        self._transfer_valid = False

    def set_camera_object(self, camera: Camera) -> None:
        self._check_usable()
        if not isinstance(camera, Camera):
            raise ArgumentTypeError(f"Renderer.set_camera_object: expected a Camera, got {type(camera).__name__}")
        self.camera = camera
        self._transfer_valid = False

    @_in_context
    def set_envmap(self, envmap, rotation=None) -> None:
        """Light with an equirectangular ``.hdr``/``.exr`` file, or a bundled map by name
        (:data:`prt.runtime.envmaps.BUNDLED_ENVMAPS`); ``rotation`` is a 3x3 matrix."""
        self._check_usable()
        if not isinstance(envmap, (str, os.PathLike)):
            raise ArgumentTypeError(f"Renderer.set_envmap: expected a bundled name or a path, got {type(envmap).__name__}")
        path = bundled_envmap_path(envmap) if isinstance(envmap, str) and envmap in BUNDLED_ENVMAPS else envmap
        key = str(Path(path).resolve()) if Path(path).exists() else str(path)
        if key not in self._envmap_sh:  # turning the light must not re-read and re-project the file
            self._envmap_sh[key] = load_envmap_sh(path, self.scene.manifest.sh_bands)
        self.lighting = Lighting.from_sh(self._envmap_sh[key], rotation=rotation)
        self._envmap_path, self._envmap_rotation = Path(path), rotation

    @_in_context
    def set_lighting_sh(self, coeffs, rotation=None) -> None:
        """Light with SH coefficients (16, 3), finite in float32."""
        self._check_usable()
        lighting = Lighting.from_sh(coeffs, rotation=rotation)
        if lighting.bands != self.scene.manifest.sh_bands:
            n = self.scene.manifest.sh_bands
            raise InputError(f"Renderer.set_lighting_sh: the scene has {n} SH bands ({n * n} rows), got {lighting.bands} bands ({lighting.sh.shape[0]} rows)")
        self.lighting = lighting
        self._envmap_path = None  # no image to draw behind the geometry

    @_in_context
    def set_deformation(self, theta=None, *, frame=None) -> None:
        """Deformable scenes (``scene.deformation``): pose the object by a recorded ``frame`` (index)
        or by a shape code ``theta`` (d numbers; the pose is the rest plus the code's PCA offsets).
        The next :meth:`render` draws the new pose and runs the networks once with its code;
        relighting after it stays free.

        Raises
        ------
        InputError
            If the scene is not deformable, the frame is out of range or theta has the wrong length.
        """
        self._check_usable()
        deformation = self.scene.deformation
        if deformation is None:
            raise InputError(f"{self.scene.path}: set_deformation: the scene is not deformable (built without --deform)")
        vertices, code = deformation.pose(frame=frame, theta=theta)
        self.gbuffer.set_pose(vertices)
        self._code = code
        for backend in self._backends.values():
            backend.set_code(code)
        self.pose = {"frame": None if frame is None else int(frame), "theta": code.tolist()}
        self._transfer_valid = False

    @_in_context
    def set_background(self, envmap: bool) -> None:
        """Draw the env map of the light where no geometry is (True), or black (False); a
        manifest's ``lighting.background`` sets the default.  Runs no network."""
        self._check_usable()
        if not isinstance(envmap, bool):
            raise ArgumentTypeError(f"Renderer.set_background: expected True or False, got {type(envmap).__name__}")
        self.background = envmap

    @_in_context
    def set_material(self, kind: str = "diffuse", *, object: str | None = None, **params) -> None:
        """``"diffuse"`` (albedo) or ``"glossy"`` (albedo, specular, exponent).

        Without ``object`` every object takes this material (replacing the file's per-object
        materials); with ``object="name"`` (a name in ``scene.manifest.geometry.objects``) only
        that one.  A material set here has no albedo texture (the object's texture, if any, is
        dropped).  Neither runs a network: transfer does not depend on the material.
        """
        self._check_usable()
        try:
            material = Material(kind=kind, **params)
        except ArgumentTypeError:
            raise
        except TypeError as exc:  # an unknown parameter name
            raise ArgumentTypeError(f"material: {exc}") from None
        if object is None:
            self.material = material
            self.materials.set_all(material)
            return
        self.materials.set(object, material)
        if self.materials.uniform:
            self.material = self.materials[0]
        elif self.gbuffer.material_texture is None and self.gbuffer.kind in ("mesh", "mixed"):
            # The first per-object material of a scene built without any: pixels need object ids.
            old = self.gbuffer
            self.gbuffer = self._resources.keep(GBufferPass(self.ctx, self.scene.manifest, self.width, self.height, object_materials=True))
            self._resources.objects.remove(old)
            old.release()
            self._transfer_valid = False

    def _per_object_shading(self) -> bool:
        """Whether pixels are shaded with their object's material (else with self.material)."""
        return self.gbuffer.material_texture is not None and not self.materials.uniform

    @_in_context
    def set_backend(self, backend: str) -> None:
        self._check_usable()
        _check_backend(backend)
        if backend != self.backend:
            self.backend = backend
            self._transfer_valid = False

    # ------------------------------------------------------------------ frames

    @_in_context
    def render(self) -> np.ndarray:
        """One frame: (H, W, 3) float32 linear radiance, row 0 at the top, background 0 (or the
        env map, :meth:`set_background`).

        :meth:`draw`, then the pixels: a frame shaded on the GPU is read back (timed apart, stage
        ``frame_readback``, not in ``frame``).

        Raises
        ------
        FrameError
            If the transfer (after inference, either backend) or the image holds NaN or Inf.
        RendererStateError
            After :meth:`close`, or from a thread other than the creator.
        """
        self._check_usable()
        self._draw(check=False)
        return self._read()

    @_in_context
    def read_frame(self) -> np.ndarray:
        """The pixels of the frame :meth:`draw` drew last, as :meth:`render` returns them (a GPU frame
        read back now, stage ``frame_readback``; a CPU frame as it is)."""
        self._check_usable()
        if not self.stats["frames"]:
            raise RendererStateError("Renderer.read_frame: no frame drawn yet; call draw() or render()")
        return self._read()

    def _read(self) -> np.ndarray:
        if self._transfer_on_cpu:
            return self._cpu_image
        t0 = time.perf_counter()
        self._out_fbo.read_into(self._image, components=4, dtype="f4")
        broken = int(np.count_nonzero(self._image[..., 3] > 1.5))  # shade_pass.frag's flag
        if broken:
            self._refuse_gpu_frame(broken)
        image = np.ascontiguousarray(self._image[::-1, :, :3])
        bad = count_nonfinite(image)  # the background is finite
        if bad:
            raise FrameError(self._nonfinite_message(bad))
        self.timings["frame_readback"] = 1e3 * (time.perf_counter() - t0)
        return image

    @_in_context
    def draw(self) -> None:
        """One frame drawn and finished where it is shaded, its pixels not read back.

        A frame shaded on the GPU (the ``glsl`` and ``texture`` backends) stays in
        :attr:`frame_texture` (RGBA32F linear radiance, GL's row order: row 0 at the bottom, alpha
        1 on geometry and on the background, 0 elsewhere), the background composited there; a
        window draws it without a read-back.  The ONNX backend's frame is shaded on the CPU, into
        the array :meth:`render` returns.  ``timings["frame"]`` is the frame as its user sees it:
        G-buffer, transfer, shading (and background), finished (``glFinish``).

        Raises
        ------
        FrameError
            As :meth:`render` (a GPU frame is checked by an occlusion query, not by reading it).
        """
        self._check_usable()
        self._draw(check=True)

    @property
    def frame_texture(self) -> moderngl.Texture | None:
        """The last frame's texture when it was shaded on the GPU (see :meth:`draw`), else None."""
        return None if self._closed or self._transfer_on_cpu else self._out_texture

    @property
    def gl_renderer(self) -> str:
        """The GL_RENDERER string of the context that draws the frames (``"llvmpipe (LLVM ...)"``,
        ``"NVIDIA H200/PCIe/SSE2"``): which device drew a frame."""
        return str(self.ctx.info.get("GL_RENDERER", ""))

    def _draw(self, check: bool) -> None:
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
            # Shaded rows scattered once into a fresh image: 0 where no geometry is, or the env map
            # (drawn only there, copied; its time is the stage "background").
            image = self._background_base(timings)
            scatter_rows(image, self._covered, radiance)
            bad = count_nonfinite(radiance)  # the background is 0 or the finite map
            if bad:
                raise FrameError(self._nonfinite_message(bad))
            self._cpu_image = image.reshape(self.height, self.width, 3)
            timings["shade"] = 1e3 * (t1 - t0)
            timings["readout"] = 1e3 * (time.perf_counter() - t1) - timings.get("background", 0.0)
        else:
            self._shade_gl()
            if self._background_on():  # on the GPU, where the G-buffer's depth is 1
                self.ctx.finish()
                t1 = time.perf_counter()
                self._background_layer(into=self._out_texture)
                timings["background"] = 1e3 * (time.perf_counter() - t1)
            self.ctx.finish()
            timings["shade"] = 1e3 * (time.perf_counter() - t0) - timings.get("background", 0.0)
            if check:
                t1 = time.perf_counter()
                if self._flags is None:
                    self._flags = self._resources.keep(FlagCounter(self.ctx, (self.width, self.height)))
                broken = self._flags.count(self._out_texture)
                if broken:
                    self._refuse_gpu_frame(broken)
                timings["check"] = 1e3 * (time.perf_counter() - t1)
        timings["frame"] = 1e3 * (time.perf_counter() - t_frame)
        self.timings = timings
        self.stats["frames"] += 1

    def _refuse_gpu_frame(self, broken: int) -> None:
        message = self._broken_transfer_message(broken)
        self._transfer_valid = False
        raise FrameError(message)

    def _nonfinite_message(self, bad: int) -> str:
        return (f"{self.scene.path}: the frame has {bad} NaN or Inf values after shading (lighting or material too "
                "large for float32?); no image returned")  # fmt: skip

    def _background_on(self) -> bool:
        return self.background and self._envmap_path is not None

    def _background_layer(self, into: moderngl.Texture | None = None, draw_only: bool = False) -> np.ndarray | None:
        """(H, W, 3) the env map seen by the camera where the G-buffer has no geometry, 0 elsewhere
        (drawn there only: the G-buffer's depth for this camera masks the rest); cached, not a copy.
        ``into``: drawn into that texture instead (a frame shaded on the GPU), nothing read back.
        ``draw_only``: drawn into the layer's own target now, read back by the next call."""
        if self._background is None:
            self._background = self._resources.keep(EnvmapBackground(self.ctx, self.width, self.height))
        self._background.set_envmap(self._envmap_path, str(self._envmap_path))
        view = (self.camera, self._envmap_rotation, self.gbuffer.depth_texture)
        if into is not None:
            return self._background.draw_into(into, *view)
        if draw_only:
            return self._background.draw_layer(*view, generation=self._gbuffer_generation)
        return self._background.image(*view, generation=self._gbuffer_generation)

    def _background_base(self, timings: dict) -> np.ndarray:
        """A fresh (H * W, 3) image to scatter shaded rows into: the background layer, or 0."""
        if not self._background_on():
            return np.zeros((self.height * self.width, 3), dtype=np.float32)
        t0 = time.perf_counter()
        image = np.empty((self.height * self.width, 3), dtype=np.float32)
        np.copyto(image.reshape(self.height, self.width, 3), self._background_layer())
        timings["background"] = 1e3 * (time.perf_counter() - t0)
        return image

    def render_srgb(self, exposure=None) -> np.ndarray:
        """One frame tone-mapped for display: (H, W, 3) uint8 sRGB, at ``exposure`` (default :attr:`exposure`;
        ``"auto"``: this frame's :meth:`frame_exposure`, not smoothed)."""
        exposure = self.exposure if exposure is None else parse_exposure(exposure, "render_srgb: exposure")
        image = self.render()
        return to_srgb8(image, self.frame_exposure(image) if exposure == "auto" else exposure)

    def set_exposure(self, exposure) -> None:
        """``"auto"`` or a number >= 0: the exposure :meth:`render_srgb` (and the viewer, the headless paths) use."""
        self.exposure = parse_exposure(exposure, "Renderer.set_exposure")

    @_in_context
    def frame_exposure(self, image: np.ndarray | None = None) -> float:
        """The auto exposure of the last frame over the pixels it covers (:mod:`prt.runtime.exposure_gl`;
        a GPU frame reduced there). ``image``: that frame as :meth:`render` returned it."""
        return exposure_gl.frame_exposure(self, image)

    @_in_context
    def covered_mask(self) -> np.ndarray:
        """(H, W) bool, row 0 at the top: the pixels the last frame's geometry covers."""
        return exposure_gl.covered_mask(self)

    @_in_context
    def render_transfer(self) -> np.ndarray:
        """The transfer image of the current view: (H, W, 16) float32, row 0 at the top ((H, W, 64) with
        interreflection: direct, indirect R, G, B)."""
        self._check_usable()
        if not self._transfer_valid:
            self._compute_transfer({})
            self.stats["network_runs"] += 1
        if self._transfer_on_cpu:
            full = np.zeros((self.height * self.width, self._transfer_width), dtype=np.float32)
            full[self._covered] = self._transfer_cov
            return full.reshape(self.height, self.width, self._transfer_width)
        parts = []
        for tex in self._t_textures:
            a = np.frombuffer(tex.read(), dtype=np.float32).reshape(self.height, self.width, 4)
            parts.append(a[::-1])
        transfer = np.concatenate(parts, axis=2)
        bad = int(np.count_nonzero(~np.isfinite(transfer).all(axis=2)))
        if bad:
            raise FrameError(self._broken_transfer_message(bad))
        return transfer

    @_in_context
    def gbuffer_image(self):
        """The G-buffer of the current view (see :class:`prt.runtime.gbuffer.GBuffer`)."""
        self._check_usable()
        self.gbuffer.render(self.camera)
        return self.gbuffer.read()

    # ------------------------------------------------------------------ stages

    def _compute_transfer(self, timings: dict) -> None:
        t0 = time.perf_counter()
        backend = self._backend()
        self.gbuffer.render(self.camera)
        self._gbuffer_generation += 1
        if self.background_with_gbuffer and backend.on_cpu and self._background_on():  # one wait for both passes
            self._background_layer(draw_only=True)
        self.ctx.finish()
        t1 = time.perf_counter()
        result = backend.run(self.gbuffer, self._t_fbo)
        timings.update({"gbuffer": 1e3 * (t1 - t0), **backend.timings})
        self.stats["network_fraction"] = float(getattr(backend, "fraction", 1.0))
        if result is not None:
            self._take_cpu_transfer(result)
            rows = self.gbuffer.read_material()
            self._object_ids_cov, self._uv_cov = (None, None) if rows is None else (rows[0][self._covered], rows[1][self._covered])
        self._transfer_on_cpu = result is not None
        self._transfer_valid = True

    def _take_cpu_transfer(self, result: CpuTransfer) -> None:
        if not all_finite(result.transfer):  # per row only when some value is not
            bad = ~np.isfinite(result.transfer).all(axis=1)
            segments = np.unique(np.asarray(result.segment)[bad].astype(np.int64))
            raise FrameError(self._broken_segments_message(int(bad.sum()), segments))
        self._covered, self._transfer_cov = result.covered, result.transfer
        self._inputs, self._geometry_cov = result.inputs, None

    def _shade_cpu(self) -> np.ndarray:
        """Radiance of the covered pixels (M, 3) from the cached transfer (numpy twin of the shader)."""
        # BLAS worker threads spinning after these small products steal the cores from ONNX
        # Runtime's threads in the next frame; one thread is as fast for them.
        # Overflow is not warned about here: render() refuses a frame that is not finite.
        with _blas_controller().limit(limits=1, user_api="blas"), np.errstate(over="ignore", invalid="ignore"):
            return self._shade_cpu_products()

    def _shade_cpu_products(self) -> np.ndarray:
        per_object = self._per_object_shading() and self._object_ids_cov is not None
        material = self.materials[0] if self.materials.uniform else self.material
        if not per_object and material.kind == "diffuse":  # the common case, in float32: T @ (albedo * L)
            light = diffuse_light_matrix(self.lighting, material.albedo, self._transfer_cov.shape[1])  # 4 n wide: + indirect R, G, B
            return np.maximum(self._transfer_cov @ light, 0.0)
        if self._geometry_cov is None:
            rows = self._inputs  # position, normal of each covered pixel
            world = self.gbuffer.read_world()  # deformable scenes: the inputs hold the rest position
            position = rows[:, 0:3] if world is None else world[self._covered]
            self._geometry_cov = (rows[:, 3:6], self.camera.eye[None, :] - position)
        normals, view_dirs = self._geometry_cov
        if per_object:
            return shade_objects(self._transfer_cov, self._object_ids_cov, normals, view_dirs, self.lighting, self.materials, self._uv_cov)
        return shade(self._transfer_cov, normals, view_dirs, self.lighting, material)

    def _shade_gl(self) -> None:
        program, vao = self._shade_program, self._vao
        material = self.materials[0] if self.materials.uniform else self.material
        extra = []
        if self._per_object_shading():
            program, vao, table = self._material_program()
            extra = [(self.gbuffer.material_texture, 6), (table, 7), (self._material_gl["albedo"], 8)]
            program["u_albedo_textures"].value = 8
            program["u_gbuffer_material"].value = 6
            program["u_material_table"].value = 7
        for name, value in shader_uniforms(self.lighting, material).items():
            if name in program:
                program[name].write(np.ascontiguousarray(value).tobytes())
        program["u_eye"].value = tuple(float(v) for v in self.camera.eye)
        position = self.gbuffer.world_texture if self.gbuffer.world_texture is not None else self.gbuffer.position_texture  # view directions
        textures = [(position, 0), (self.gbuffer.normal_texture, 1)]
        for k, tex in enumerate(self._t_textures):  # units 2..5; the indirect transfer's 9..20 (after the materials')
            textures.append((tex, 2 + k if k < 4 else 5 + k))
            program[f"u_t{k}"].value = 2 + k if k < 4 else 5 + k
        program["u_position"].value = 0
        program["u_normal"].value = 1
        draw_fullscreen(self.ctx, self._out_fbo, vao, textures + extra)

    def _shade_defines(self) -> dict:
        """The shade pass's defines: the shading's, and PRT_INTERREFLECTION for RGB transfer."""
        return {**GLSL_DEFINES, "PRT_INTERREFLECTION": 1} if self._transfer_width > 16 else dict(GLSL_DEFINES)

    def _material_program(self):
        """The shade program with per-object materials and its table texture (built on first use,
        the table re-uploaded after each set_material)."""
        gl = self._material_gl
        if "program" not in gl:
            source = assemble(*GLSL_FILES, "shade_pass.frag", defines={**self._shade_defines(), "PRT_OBJECT_MATERIALS": 1})
            gl["program"] = self._resources.keep(compile_program(self.ctx, source, "shade_pass.frag (materials)"))
            gl["vao"] = self._resources.keep(self.ctx.vertex_array(gl["program"], []))
            gl["albedo"] = self._resources.keep((self.materials.textures or AlbedoTextures([])).gl_texture(self.ctx))
        if gl.get("version") != self.materials.version or "table" not in gl:
            data = self.materials.texture_data()  # (rows, K, 4)
            if "table" in gl and gl["table"].size != (data.shape[1], data.shape[0]):
                self._resources.objects.remove(gl["table"])
                gl.pop("table").release()
            if "table" not in gl:
                gl["table"] = self._resources.keep(self._float_texture((data.shape[1], data.shape[0])))
            gl["table"].write(np.ascontiguousarray(data).tobytes())
            gl["version"] = self.materials.version
        return gl["program"], gl["vao"], gl["table"]

    def _backend(self) -> TransferBackend:
        if self.backend not in self._backends:
            backend = create_backend(self.backend, self.ctx, self.scene.manifest, **self._backend_options)
            self._backends[self.backend] = backend
            if self._code is not None:
                backend.set_code(self._code)
        return self._backends[self.backend]

    def _broken_transfer_message(self, pixels: int) -> str:
        """The FrameError text for a GPU transfer flagged non-finite: which segments (read back only now)."""
        packed = self.gbuffer.read_packed()
        parts = [np.frombuffer(t.read(), dtype=np.float32).reshape(self.height, self.width, 4)[::-1] for t in self._t_textures]
        rows = np.flatnonzero(~np.isfinite(np.concatenate(parts, axis=2).reshape(-1, self._transfer_width)).all(axis=1))
        segments = np.unique(packed[rows, PACKED_SEGMENT].astype(np.int64)) if len(rows) else np.zeros(0, np.int64)
        return self._broken_segments_message(pixels, segments[segments >= 0])

    def _broken_segments_message(self, pixels: int, segments: np.ndarray) -> str:
        files = [str(self.scene.manifest.segments[s].model or self.scene.manifest.segments[s].glsl or f"segment {s}")
                 for s in segments.tolist() if 0 <= s < len(self.scene.manifest.segments)]  # fmt: skip
        where = f" from {', '.join(files)}" if files else ""
        return (f"{self.scene.path}: the transfer is NaN or Inf at {pixels} pixels{where} (backend {self.backend}); "
                "the network is broken, no image returned")  # fmt: skip

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
        """Release GPU resources and ONNX sessions (also on ``with`` exit); closing twice is harmless."""
        if self._closed:
            return
        if threading.get_ident() != self._owner:
            self._check_usable()  # the GL context is current in the creator's thread only
        self._closed = True
        self._finalizer.detach()
        self._resources.release(True)

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _check_backend(backend) -> None:
    if not isinstance(backend, str):
        raise ArgumentTypeError(f"backend must be one of {ALL_BACKENDS}, got {type(backend).__name__} {backend!r}")
    if backend not in ALL_BACKENDS:
        raise InputError(f"backend must be one of {ALL_BACKENDS}, got {backend!r}")


def _check_size(ctx: moderngl.Context, width: int, height: int) -> None:
    """InputError for an image size beyond what the GL driver can allocate (its texture, renderbuffer and viewport limits)."""
    limits = [ctx.info.get("GL_MAX_TEXTURE_SIZE"), ctx.info.get("GL_MAX_RENDERBUFFER_SIZE")]
    viewport = ctx.info.get("GL_MAX_VIEWPORT_DIMS")
    limit = min(int(v) for v in limits + list(viewport or ()) if v)
    if width > limit or height > limit:
        raise InputError(f"image size {width}x{height}: this OpenGL driver allows at most {limit}x{limit}")


def _check_allocation(ctx: moderngl.Context, width: int, height: int) -> None:
    """InputError if the driver failed to allocate the frame buffers (GL_OUT_OF_MEMORY and the like)."""
    error = ctx.error
    if error != "GL_NO_ERROR":
        raise InputError(f"image size {width}x{height}: the OpenGL driver cannot allocate the frame buffers ({error})")


def all_finite(values: np.ndarray) -> bool:
    """``np.isfinite(values).all()`` in two reductions and no temporary: min and max propagate NaN."""
    return values.size == 0 or bool(np.isfinite(np.min(values)) and np.isfinite(np.max(values)))


@functools.lru_cache(maxsize=1)
def _blas_controller():
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()
