"""The interactive viewer window (pygame + the window's OpenGL context).

Controls (also printed on ``h``):
  left drag        orbit the camera          wheel        zoom
  right drag / [ ] rotate the light          n / p        next / previous env map
  b                toggle backend onnx/glsl  g            diffuse / glossy
  + / -            Phong exponent x2 / /2    e / E        exposure (auto: its bias) up / down
  x                auto exposure on / off    k            env-map background on/off
  s / F12          screenshot (PNG; F12 also while walking)
  v                walk (first person) / orbit
    walking: W A S D or arrows move, left drag looks, space / ctrl up / down, shift x4 faster
  c                save the camera path (the moves so far; the orbit if none)
  o                save the orbit of the current view as a camera path
  h                help                      q / Esc      quit
  a                play / pause the recorded poses (deformable scenes)
  , / .            previous / next pose (deformable scenes)
Walking moves at a tenth of the scene box's diagonal per second (prt.runtime.camera.walk_speed);
the moves are recorded as the orbit's are (c saves them as a camera path).  Auto exposure (the
default for scenes) follows each frame's log-average luminance, smoothed over about half a second.
The title shows the FPS of frames that ran the networks (camera moves) and, apart, the time
of re-shading the cached transfer (light, material: no network runs), labelled "relight";
the stage times of network frames are printed here.
While the camera moves the frame is rendered smaller and upscaled to hold --target-fps;
when it stops, the view is rendered again at full resolution.
"""

from __future__ import annotations

import filecmp
import time
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import moderngl
import numpy as np

from ..shaders import assemble
from .backends import BACKENDS
from .camera import fit_near, scene_box, walk, walk_speed
from .camera_path import PathRecorder, orbit_path, save_camera_path
from .exposure import ExposureAdapter
from .envmaps import BUNDLED_ENVMAPS, DEFAULT_ENVMAP, bundled_envmap_path
from .errors import PRTError
from .gl import compile_program
from .materials import apply_object_albedo
from .renderer import Renderer
from .shading import GLSL_DEFINES, to_srgb8

__all__ = ["run_window", "ViewerOptions", "HELP", "DynamicResolution", "envmap_cycle", "title_text", "stage_text",
           "walk_move", "held_actions", "WALK_FAST", "LOOK_SENSITIVITY"]

HELP = __doc__.split("Controls (also printed on ``h``):\n", 1)[1]
ENVMAPS = tuple(BUNDLED_ENVMAPS)
ORBIT_FRAMES = 120  # frames of a saved orbit (4 s at 30 FPS)
WALK_FAST = 4.0  # shift's speed factor while walking
LOOK_SENSITIVITY = 0.005  # radians of mouse look per pixel dragged
WALK_KEYS = {"forward": ("K_w", "K_UP"), "back": ("K_s", "K_DOWN"), "left": ("K_a", "K_LEFT"), "right": ("K_d", "K_RIGHT"),
             "up": ("K_SPACE",), "down": ("K_LCTRL", "K_RCTRL"), "fast": ("K_LSHIFT", "K_RSHIFT")}  # fmt: skip
WALK_LETTERS = "wasd"  # keys that move while walking instead of their orbit meaning (a: poses, s: screenshot)


@dataclass(frozen=True)
class ViewerOptions:
    """What the viewer (and the headless orbit) starts with; ``prt-runtime`` builds it from its flags.

    ``envmap`` is a bundled name or a file (None: the scene's light); ``material`` overrides
    the scene's kind (None: keep it), keeping its albedo, with ``exponent`` for glossy;
    ``background`` draws the env map behind the geometry (None: the scene's choice);
    ``target_fps`` is the window's dynamic-resolution goal while the camera moves (None: off).
    """

    width: int = 512
    height: int = 512
    backend: str = BACKENDS[0]
    envmap: str | None = None
    material: str | None = None
    exponent: float = 16.0
    exposure: float | str | None = None  # a number or "auto"; None: the scene's (Renderer.exposure)
    providers: list[str] | None = None
    threads: int | None = None
    background: bool | None = None
    target_fps: float | None = 30.0
    object_albedo: tuple = ()  # ((object name, (r, g, b)), ...): per-object albedo overrides
    interpolate: float | None = None  # the ONNX backend's screen-space interpolation tolerance (runtime/interpolation.py); None: every pixel
    gl_device: str | None = None  # headless: the EGL device (runtime/gl_devices.py); None: $PRT_GL_DEVICE, else auto

    def renderer(self, scene, ctx: moderngl.Context | None = None, size: tuple[int, int] | None = None) -> Renderer:
        """A :class:`Renderer` of ``scene`` at this size (or ``size``) and backend, with the options applied."""
        width, height = size or (self.width, self.height)
        r = Renderer(scene, width, height, backend=self.backend, providers=self.providers, threads=self.threads, ctx=ctx,
                     interpolate=self.interpolate, gl_device=None if ctx is not None else self.gl_device)  # fmt: skip
        try:
            self.apply(r)
        except BaseException:
            r.close()
            raise
        return r

    def apply(self, r: Renderer) -> None:
        """Set the light, the material and the background of ``r`` from these options."""
        if self.envmap:
            r.set_envmap(self.envmap)
        if self.material == "glossy":
            r.set_material("glossy", albedo=r.material.albedo, specular=(0.3, 0.3, 0.3), exponent=self.exponent)
        elif self.material == "diffuse":
            r.set_material("diffuse", albedo=r.material.albedo)
        for name, albedo in self.object_albedo:
            apply_object_albedo(r, name, albedo)
        if self.background is not None:
            r.set_background(self.background)
        if self.exposure is not None:
            r.set_exposure(self.exposure)


# ---------------------------------------------------------------------------- pure parts


def envmap_cycle(custom: str | None = None, scene_envmap: Path | None = None) -> tuple[tuple[str, ...], int]:
    """The env maps ``n`` / ``p`` cycle through, and the index of the one shown first.

    The bundled maps by name, then a custom file given on the command line (``custom``, a path)
    and the scene's own map file, each unless it is one of the bundled maps (same bytes).
    The first shown is ``custom``, else the scene's map, else the default bundled map.
    """
    cycle = list(ENVMAPS)

    def entry(value) -> int:
        if str(value) in ENVMAPS:
            return ENVMAPS.index(str(value))
        path = Path(value)
        for i, name in enumerate(ENVMAPS):
            try:
                if filecmp.cmp(path, bundled_envmap_path(name), shallow=False):
                    return i
            except OSError:
                break
        if str(path) not in cycle:
            cycle.append(str(path))
        return cycle.index(str(path))

    first = ENVMAPS.index(DEFAULT_ENVMAP)
    if scene_envmap is not None:
        first = entry(scene_envmap)
    if custom:
        first = entry(custom)
    return tuple(cycle), first


def envmap_label(entry: str) -> str:
    return entry if entry in ENVMAPS else Path(entry).name


class DynamicResolution:
    """Which resolution scale to render at: full when the camera is still; while it moves, the
    largest scale whose expected frame time meets the target.

    Frame times are kept per scale (a moving average of network frames); a scale not yet
    measured is estimated from the nearest measured one, in proportion to its pixels.
    """

    SCALES = (1.0, 0.75, 0.5, 0.375, 0.25)

    def __init__(self, target_ms: float | None, scales=SCALES, smoothing: float = 0.5) -> None:
        self.target_ms = target_ms
        self.scales = tuple(sorted(scales, reverse=True))
        self.smoothing = smoothing
        self.frame_ms: dict[float, float] = {}

    def record(self, scale: float, ms: float) -> None:
        old = self.frame_ms.get(scale)
        self.frame_ms[scale] = ms if old is None else old + self.smoothing * (ms - old)

    def estimate(self, scale: float) -> float | None:
        if scale in self.frame_ms:
            return self.frame_ms[scale]
        if not self.frame_ms:
            return None
        nearest = min(self.frame_ms, key=lambda s: abs(s - scale))
        return self.frame_ms[nearest] * (scale / nearest) ** 2

    def choose(self, moving: bool) -> float:
        if not moving or not self.target_ms:
            return self.scales[0]
        for scale in self.scales:
            expected = self.estimate(scale)
            if expected is None or expected <= self.target_ms:
                return scale
        return self.scales[-1]

    @staticmethod
    def size(scale: float, width: int, height: int) -> tuple[int, int]:
        return max(1, round(width * scale)), max(1, round(height * scale))


def title_text(scene: str, backend: str, material: str, envmap: str, *, fps: float | None, size: tuple[int, int] | None,
               relight_ms: float | None = None, full: bool = True, renderer: str | None = None) -> str:
    """The window title, short enough for a 512-pixel window: the FPS of network frames (with
    their size, and "moving" when smaller than the window), the re-shading time apart, labelled
    "relight", then the backend, material and env map, and the GL renderer that draws (its name
    up to the first " (" or "/": "llvmpipe", "NVIDIA GeForce RTX 3090").  Stage times go to the terminal."""
    parts = [scene]
    if fps is not None and size is not None:
        parts.append(f"{fps:.1f} FPS {size[0]}x{size[1]}{'' if full else ' moving'}")
    if relight_ms is not None:
        parts.append(f"relight {relight_ms:.1f} ms")
    parts.append(f"{backend} {material} {envmap}")
    if renderer:
        parts.append(renderer.split(" (")[0].split("/")[0])
    return " | ".join(parts)


def stage_text(fps: float, size: tuple[int, int], stages: dict, renderer: str = "") -> str:
    """The terminal line of a network frame's stage times (and the GL renderer that drew it)."""
    on = f" on {renderer}" if renderer else ""
    return f"{fps:.1f} FPS at {size[0]}x{size[1]}{on}: " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items() if k != "frame") + " ms"


def held_actions(pressed) -> set[str]:
    """The walk actions of the keys held (``pressed``: ``pygame.key.get_pressed()``, or a mapping of key codes)."""
    import pygame

    return {action for action, names in WALK_KEYS.items() if any(pressed[getattr(pygame, name)] for name in names)}


def walk_move(actions: set[str], speed: float, dt: float) -> tuple[float, float, float] | None:
    """(forward, right, up) scene units for ``dt`` seconds of the held ``actions`` at ``speed`` units a
    second (x :data:`WALK_FAST` with "fast"); a diagonal is no faster than a straight step.  None: no move."""
    f = ("forward" in actions) - ("back" in actions)
    r = ("right" in actions) - ("left" in actions)
    u = ("up" in actions) - ("down" in actions)
    if not (f or r or u):
        return None
    step = speed * max(float(dt), 0.0) * (WALK_FAST if "fast" in actions else 1.0)
    norm = float(np.sqrt(f * f + r * r + u * u))
    return (f * step / norm, r * step / norm, u * step / norm)


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# ---------------------------------------------------------------------------- the window


class _View:
    """What the user has set; applied to whichever renderer (resolution) draws the next frame."""

    def __init__(self, r: Renderer, cycle: tuple[str, ...], envmap_index: int) -> None:
        self.base_camera = r.camera
        self.camera = r.camera
        self.cycle, self.envmap_index = cycle, envmap_index
        self.light_angle = 0.0
        self.light_changed = False  # until then each renderer keeps the scene's (or --envmap's) light
        self.material = r.material
        self.material_changed = False  # until then each renderer keeps the scene's (per-object) materials
        self._given: dict[int, object] = {}  # renderer id -> the material last set on it
        self.backend = r.backend
        self.background = r.background
        self.yaw, self.pitch, self.zoom = 0.0, 0.0, 1.0
        self.walking = False  # first person (v) instead of the orbit
        self.box = scene_box(r.scene.manifest)
        self.speed = walk_speed(self.box)
        # Deformable scenes: the recorded frame shown, and whether the poses play.
        deformation = r.scene.deformation
        self.poses = 0 if deformation is None else deformation.frame_count
        self.pose = None if deformation is None else (r.pose or {}).get("frame", 0)
        self.playing = False

    def step_pose(self, step: int) -> bool:
        """Move to the next (``step`` 1) or previous (-1) recorded pose; False when the scene has none."""
        if not self.poses:
            return False
        self.pose = (self.pose + step) % self.poses
        return True

    def toggle_walk(self) -> bool:
        """Orbit <-> walk; the orbit resumes about the view the walk ended at."""
        self.walking = not self.walking
        if not self.walking:
            self.base_camera, self.yaw, self.pitch, self.zoom = self.camera, 0.0, 0.0, 1.0
        return self.walking

    def walk_step(self, move=(0.0, 0.0, 0.0), yaw: float = 0.0, pitch: float = 0.0) -> None:
        """One first-person step (:func:`prt.runtime.camera.walk`), the near plane fitted for an interior."""
        self.camera = fit_near(walk(self.camera, move, yaw, pitch), self.box)

    def update_camera(self) -> None:
        cam = self.base_camera.orbit(self.yaw)
        cam = cam.orbit(self.pitch, axis=np.cross(cam.forward, cam.true_up))
        eye = cam.target + (cam.eye - cam.target) * self.zoom
        self.camera = type(cam)(eye, cam.target, self.base_camera.up, cam.fov_y, cam.near, cam.far)

    def apply(self, r: Renderer) -> None:
        if r.camera is not self.camera:
            r.set_camera_object(self.camera)
        if self.light_changed:
            r.set_envmap(self.cycle[self.envmap_index], rotation=_rotation_y(self.light_angle))
        m = self.material
        if self.material_changed and self._given.get(id(r)) is not m:
            r.set_material(m.kind, albedo=m.albedo, specular=m.specular, exponent=m.exponent)
            self._given[id(r)] = m
        r.set_backend(self.backend)
        r.set_background(self.background)
        if self.pose is not None and (r.pose or {}).get("frame") != self.pose:
            r.set_deformation(frame=self.pose)


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
    renderers: dict[float, Renderer] = {1.0: options.renderer(scene, ctx=ctx)}
    displays: dict[float, moderngl.Texture] = {}
    blit = compile_program(ctx, assemble("tonemap.glsl", "viewer_blit.frag", defines=GLSL_DEFINES), "viewer_blit.frag")
    blit_vao = ctx.vertex_array(blit, [])
    full = renderers[1.0]
    cycle, first = envmap_cycle(options.envmap, scene.manifest.lighting.envmap)
    view = _View(full, cycle, first)
    policy = DynamicResolution(1000.0 / options.target_fps if options.target_fps else None)
    recorder = PathRecorder()
    exposure = full.exposure  # "auto" (a scene's default) or a number; e / E scale it (auto: a bias)
    bias, adapter, shown_exposure = 1.0, ExposureAdapter(), 1.0
    last_loop = last_adapt = time.perf_counter()
    dragging = None
    network_ms: dict[tuple[int, int], list[float]] = {}  # per frame size: FPS never mixes sizes
    fps = relight_ms = last_size = None
    stages: dict = {}
    shown_scale = 1.0
    last_title = last_stages = 0.0
    print(HELP)
    running, redraw, shown = True, True, None  # shown: the renderer of the frame on screen
    try:
        while running:
            camera_moved = shade_changed = False
            now = time.perf_counter()
            dt, last_loop = min(now - last_loop, 0.1), now  # seconds since the last loop (a stall moves no further)
            for event in pygame.event.get():
                if event.type == pygame.QUIT:
                    running = False
                elif event.type == pygame.MOUSEBUTTONDOWN and event.button in (1, 3):
                    dragging = event.button
                elif event.type == pygame.MOUSEBUTTONUP:
                    dragging = None
                elif event.type == pygame.MOUSEMOTION and dragging == 1 and view.walking:
                    view.walk_step(yaw=-event.rel[0] * LOOK_SENSITIVITY, pitch=-event.rel[1] * LOOK_SENSITIVITY)
                    camera_moved = True
                elif event.type == pygame.MOUSEMOTION and dragging == 1:
                    view.yaw -= event.rel[0] * 0.01
                    view.pitch = float(np.clip(view.pitch + event.rel[1] * 0.01, -1.4, 1.4))
                    camera_moved = True
                elif event.type == pygame.MOUSEMOTION and dragging == 3:
                    view.light_angle += event.rel[0] * 0.01
                    view.light_changed = shade_changed = True
                elif event.type == pygame.MOUSEWHEEL and not view.walking:
                    view.zoom = float(np.clip(view.zoom * (0.9 if event.y > 0 else 1.1), 0.2, 5.0))
                    camera_moved = True
                elif event.type == pygame.KEYDOWN:
                    key = event.unicode
                    if view.walking and key and key.lower() in WALK_LETTERS:
                        key = ""  # a move (held_actions below), not the orbit's key
                    if event.key == pygame.K_F12:
                        key = "s"
                    if event.key == pygame.K_ESCAPE or key == "q":
                        running = False
                    elif key == "v":
                        print("walk: W A S D / arrows, left drag looks, space / ctrl up / down, shift faster; v: orbit"
                              if view.toggle_walk() else "orbit")
                    elif key == "x":
                        exposure = 1.0 if exposure == "auto" else "auto"
                        bias, redraw = 1.0, True
                        adapter.reset()
                        print(f"exposure {exposure}")
                    elif key == "h":
                        print(HELP)
                    elif key and key in "[]":
                        view.light_angle += 0.1 if key == "]" else -0.1
                        view.light_changed = shade_changed = True
                    elif key in ("n", "p"):
                        view.envmap_index = (view.envmap_index + (1 if key == "n" else -1)) % len(view.cycle)
                        view.light_changed = shade_changed = True
                    elif key == "b":
                        view.backend = BACKENDS[(BACKENDS.index(view.backend) + 1) % len(BACKENDS)] if view.backend in BACKENDS else BACKENDS[0]
                        redraw = True
                    elif key == "g":
                        m = view.material
                        kind = "glossy" if m.kind == "diffuse" else "diffuse"
                        view.material = type(m)(kind=kind, albedo=m.albedo, specular=(0.3, 0.3, 0.3) if kind == "glossy" else m.specular, exponent=m.exponent)
                        view.material_changed = shade_changed = True
                    elif key in ("+", "=", "-"):
                        m = view.material
                        e = float(np.clip(m.exponent * (2.0 if key != "-" else 0.5), 1.0, 1024.0))
                        view.material = type(m)(kind=m.kind, albedo=m.albedo, specular=m.specular, exponent=e)
                        view.material_changed = shade_changed = True
                    elif key == "k":
                        view.background = not view.background
                        shade_changed = True
                    elif key in ("e", "E"):
                        if exposure == "auto":
                            bias *= 1.25 if key == "e" else 0.8
                        else:
                            exposure *= 1.25 if key == "e" else 0.8
                        redraw = True
                    elif key == "a":
                        view.playing = bool(view.poses) and not view.playing
                    elif key in (",", "."):
                        camera_moved = view.step_pose(1 if key == "." else -1) or camera_moved
                    elif key == "s" and shown is not None:
                        path = Path(f"prt_screenshot_{time.strftime('%Y%m%d_%H%M%S')}.png")
                        iio.imwrite(path, to_srgb8(shown.render(), shown_exposure))  # the cached transfer re-shaded: no network
                        print(f"screenshot: {path}")
                    elif key in ("c", "o"):
                        recorded = recorder.path() if key == "c" else None
                        path = save_camera_path(Path(f"prt_camera_path_{time.strftime('%Y%m%d_%H%M%S')}.json"),
                                                recorded or orbit_path(view.camera, ORBIT_FRAMES))  # fmt: skip
                        what = f"{recorded.frames} recorded views" if recorded else f"orbit of {ORBIT_FRAMES} frames"
                        print(f"camera path: {path} ({what}; render it with prt-runtime --camera-path {path} --headless)")
            if view.playing:  # one recorded pose per drawn frame
                camera_moved = view.step_pose(1)
            if view.walking:
                move = walk_move(held_actions(pygame.key.get_pressed()), view.speed, dt)
                if move is not None:
                    view.walk_step(move)
                    camera_moved = True
            elif camera_moved:
                view.update_camera()
            if camera_moved:
                recorder.add(view.camera)
            moving = camera_moved or dragging == 1
            scale = policy.choose(moving)
            was_redraw, redraw = redraw, False
            if not (camera_moved or shade_changed or was_redraw or scale != shown_scale):
                pygame.time.wait(8)  # nothing changed: no frame, no busy loop
                continue
            r = renderers.get(scale)
            if r is None:
                r = renderers[scale] = options.renderer(scene, ctx=ctx, size=DynamicResolution.size(scale, width, height))
            view.apply(r)
            runs = r.stats["network_runs"]
            t0 = time.perf_counter()
            r.draw()
            shown = r
            display = r.frame_texture  # a frame shaded on the GPU is drawn from its texture: no read-back
            if display is None:  # shaded on the CPU: uploaded
                image = r.read_frame()  # the frame just drawn, no more work
                display = displays.get(scale)
                if display is None:
                    display = displays[scale] = ctx.texture((r.width, r.height), 3, dtype="f4")
                display.write(np.ascontiguousarray(image[::-1]))  # GL rows run bottom-up
            display.filter = (moderngl.LINEAR, moderngl.LINEAR)
            display.use(0)
            blit["u_image"].value = 0
            if exposure == "auto":  # the frame's log-average (reduced on the GPU for a GPU frame), smoothed
                target, now = r.frame_exposure(), time.perf_counter()
                shown_exposure = adapter.update(target, now - last_adapt) * bias
                last_adapt = now
                redraw = redraw or abs(np.log(shown_exposure / (target * bias))) > 0.01  # still adapting: draw again
            else:
                shown_exposure = exposure
            blit["u_exposure"].value = shown_exposure
            blit["u_window"].value = (float(width), float(height))
            screen.use()
            ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
            blit_vao.render(moderngl.TRIANGLES, vertices=3)
            pygame.display.flip()
            ms = 1e3 * (time.perf_counter() - t0)
            shown_scale = scale
            if r.stats["network_runs"] > runs:  # a frame that ran the networks: it counts for FPS
                policy.record(scale, ms)
                last_size = (r.width, r.height)
                times = network_ms[last_size] = [*network_ms.get(last_size, [])[-9:], ms]
                fps, stages = 1000.0 / float(np.median(times)), dict(r.timings)
            else:  # the cached transfer re-shaded (light, material, background, exposure)
                relight_ms = ms
            now = time.perf_counter()
            if now - last_title > 0.25 or not moving:
                pygame.display.set_caption(title_text(
                    scene.name, view.backend, view.material.kind, envmap_label(view.cycle[view.envmap_index]),
                    fps=fps, size=last_size, relight_ms=relight_ms, full=last_size == (width, height), renderer=r.gl_renderer,
                ))  # fmt: skip
                last_title = now
            if fps is not None and now - last_stages > 2.0 and not moving:
                print(stage_text(fps, last_size, stages, r.gl_renderer), flush=True)
                last_stages = now
    finally:
        for texture in displays.values():
            texture.release()
        for r in renderers.values():
            r.close()
        pygame.quit()
    return 0
