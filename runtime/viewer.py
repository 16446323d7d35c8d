"""The interactive viewer window (pygame + the window's OpenGL context).

Controls (also printed on ``h``):
  left drag        orbit the camera          wheel        zoom
  right drag / [ ] rotate the light          n / p        next / previous env map
  b                toggle backend onnx/glsl  g            diffuse / glossy
  + / -            Phong exponent x2 / /2    e / E        exposure up / down
  s                screenshot (PNG)          h            help          q / Esc   quit
FPS and stage timings are shown in the window title.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import moderngl
import numpy as np

from ..shaders import assemble
from .backends import BACKENDS
from .envmaps import BUNDLED_ENVMAPS, DEFAULT_ENVMAP
from .errors import PRTError
from .gl import compile_program
from .renderer import Renderer
from .shading import GLSL_DEFINES, to_srgb8

__all__ = ["run_window", "ViewerOptions", "HELP"]

HELP = __doc__.split("Controls (also printed on ``h``):\n", 1)[1]
ENVMAPS = tuple(BUNDLED_ENVMAPS)


@dataclass(frozen=True)
class ViewerOptions:
    """What the viewer (and the headless orbit) starts with; ``prt-runtime`` builds it from its flags.

    ``envmap`` is a bundled name or a file (None: the scene's light); ``material`` overrides
    the scene's kind (None: keep it), keeping its albedo, with ``exponent`` for glossy.
    """

    width: int = 512
    height: int = 512
    backend: str = BACKENDS[0]
    envmap: str | None = None
    material: str | None = None
    exponent: float = 16.0
    exposure: float = 1.0
    providers: list[str] | None = None
    threads: int | None = None

    def renderer(self, scene, ctx: moderngl.Context | None = None) -> Renderer:
        """A :class:`Renderer` of ``scene`` at this size and backend, with the options applied."""
        r = Renderer(scene, self.width, self.height, backend=self.backend, providers=self.providers,
                     threads=self.threads, ctx=ctx)  # fmt: skip
        try:
            self.apply(r)
        except BaseException:
            r.close()
            raise
        return r

    def apply(self, r: Renderer) -> None:
        """Set the light and the material of ``r`` from these options."""
        if self.envmap:
            r.set_envmap(self.envmap)
        if self.material == "glossy":
            r.set_material("glossy", albedo=r.material.albedo, specular=(0.3, 0.3, 0.3), exponent=self.exponent)
        elif self.material == "diffuse":
            r.set_material("diffuse", albedo=r.material.albedo)


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def run_window(scene, options: ViewerOptions) -> int:
    """Open the viewer window on ``scene``; returns the exit code."""
    try:
        import pygame  # optional: the [viewer] extra
    except ImportError:
        raise PRTError('the viewer window needs pygame (pip install "prt-runtime[viewer]"); or pass --headless') from None

    width, height = options.width, options.height
    pygame.init()
    pygame.display.gl_set_attribute(pygame.GL_CONTEXT_MAJOR_VERSION, 3)
    pygame.display.gl_set_attribute(pygame.GL_CONTEXT_MINOR_VERSION, 3)
    pygame.display.gl_set_attribute(pygame.GL_CONTEXT_PROFILE_MASK, pygame.GL_CONTEXT_PROFILE_CORE)
    try:
        pygame.display.set_mode((width, height), pygame.OPENGL | pygame.DOUBLEBUF)
        ctx = moderngl.create_context()
    except Exception as exc:  # pygame.error or moderngl.Error: no usable window context
        pygame.quit()
        raise PRTError(f"cannot open an OpenGL 3.3 window ({' '.join(str(exc).split())}); pass --headless") from None
    screen = ctx.detect_framebuffer()
    renderer = options.renderer(scene, ctx=ctx)
    blit = compile_program(ctx, assemble("tonemap.glsl", "viewer_blit.frag", defines=GLSL_DEFINES), "viewer_blit.frag")
    blit_vao = ctx.vertex_array(blit, [])
    display = ctx.texture((width, height), 3, dtype="f4")
    envmap_index = ENVMAPS.index(options.envmap) if options.envmap in ENVMAPS else ENVMAPS.index(DEFAULT_ENVMAP)
    light_angle = 0.0
    exposure = options.exposure
    base_camera = renderer.camera
    yaw, pitch, zoom = 0.0, 0.0, 1.0
    dragging = None
    print(HELP)
    frame_times = []
    running = True
    image = renderer.render()
    try:
        while running:
            camera_dirty = False
            for event in pygame.event.get():
                if event.type == pygame.QUIT:
                    running = False
                elif event.type == pygame.MOUSEBUTTONDOWN and event.button in (1, 3):
                    dragging = event.button
                elif event.type == pygame.MOUSEBUTTONUP:
                    dragging = None
                elif event.type == pygame.MOUSEMOTION and dragging == 1:
                    yaw -= event.rel[0] * 0.01
                    pitch = float(np.clip(pitch + event.rel[1] * 0.01, -1.4, 1.4))
                    camera_dirty = True
                elif event.type == pygame.MOUSEMOTION and dragging == 3:
                    light_angle += event.rel[0] * 0.01
                    _relight(renderer, envmap_index, light_angle)
                elif event.type == pygame.MOUSEWHEEL:
                    zoom = float(np.clip(zoom * (0.9 if event.y > 0 else 1.1), 0.2, 5.0))
                    camera_dirty = True
                elif event.type == pygame.KEYDOWN:
                    key = event.unicode
                    if event.key == pygame.K_ESCAPE or key == "q":
                        running = False
                    elif key == "h":
                        print(HELP)
                    elif key in "[]" and key:
                        light_angle += 0.1 if key == "]" else -0.1
                        _relight(renderer, envmap_index, light_angle)
                    elif key in ("n", "p"):
                        envmap_index = (envmap_index + (1 if key == "n" else -1)) % len(ENVMAPS)
                        _relight(renderer, envmap_index, light_angle)
                    elif key == "b":
                        renderer.set_backend(BACKENDS[(BACKENDS.index(renderer.backend) + 1) % len(BACKENDS)])
                    elif key == "g":
                        m = renderer.material
                        if m.kind == "diffuse":
                            renderer.set_material("glossy", albedo=m.albedo, specular=(0.3, 0.3, 0.3), exponent=m.exponent)
                        else:
                            renderer.set_material("diffuse", albedo=m.albedo)
                    elif key in ("+", "=", "-"):
                        m = renderer.material
                        e = float(np.clip(m.exponent * (2.0 if key != "-" else 0.5), 1.0, 1024.0))
                        renderer.set_material(m.kind, albedo=m.albedo, specular=m.specular, exponent=e)
                    elif key in ("e", "E"):
                        exposure *= 1.25 if key == "e" else 0.8
                    elif key == "s":
                        path = Path(f"prt_screenshot_{time.strftime('%Y%m%d_%H%M%S')}.png")
                        iio.imwrite(path, to_srgb8(image, exposure))
                        print(f"screenshot: {path}")
            if camera_dirty:
                cam = base_camera.orbit(yaw)
                axis = np.cross(cam.forward, cam.true_up)
                cam = cam.orbit(pitch, axis=axis)
                eye = cam.target + (cam.eye - cam.target) * zoom
                renderer.set_camera(eye=eye, target=cam.target, up=base_camera.up, fov=cam.fov_y)
            t0 = time.perf_counter()
            image = renderer.render()
            display.write(np.ascontiguousarray(image[::-1]))  # GL rows run bottom-up
            display.use(0)
            blit["u_image"].value = 0
            blit["u_exposure"].value = exposure
            screen.use()
            ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
            blit_vao.render(moderngl.TRIANGLES, vertices=3)
            pygame.display.flip()
            frame_times.append(time.perf_counter() - t0)
            if len(frame_times) >= 10:
                fps = 1.0 / float(np.median(frame_times))
                stages = " ".join(f"{k} {v:.0f}" for k, v in renderer.timings.items() if k != "frame")
                pygame.display.set_caption(
                    f"prt-runtime {scene.name} [{renderer.backend}, {renderer.material.kind}, {ENVMAPS[envmap_index]}] {fps:.1f} FPS | {stages} ms"
                )
                frame_times.clear()
    finally:
        display.release()
        renderer.close()
        pygame.quit()
    return 0


def _relight(renderer, envmap_index: int, angle: float) -> None:
    renderer.set_envmap(ENVMAPS[envmap_index], rotation=_rotation_y(angle))

