"""Mitsuba 3 as an independent reference: the scene as built, path traced (``prt-bench --reference mitsuba``).

Mitsuba shares nothing with the renderer but the scene's data, and it is given them in the
renderer's conventions (docs/design.md, "Conventions"):

- **Geometry**: ``geometry.npz`` as it is (scene space), unwelded so that every corner carries
  the normal the G-buffer interpolates (:func:`prt.runtime.normals.corner_normals`: area-weighted
  vertex normals, the face normal past 40-degree creases).  Mitsuba interpolates them
  barycentrically and normalises them, as the rasteriser does, and uses them as its shading
  normals.  Degenerate faces (no normal, no area) are left out.
- **Materials**: diffuse, one RGB albedo per object (:func:`scene_albedos`: the albedos the
  build's bounces used, else the per-object materials, else the scene's); open (two-sided)
  faces are wrapped in Mitsuba's ``twosided``, so the side a ray sees is lit, as the runtime
  shades the side facing the camera.
- **Light**: the scene's SH lighting (rotation applied) evaluated on Mitsuba's envmap grid: a
  map that holds bands 0-3 only, so 16 coefficients represent it exactly and the renderer's
  ``dot(T, L)`` is exact for it (:func:`band_limited_envmap`).  Where the 4-band radiance is
  negative (a sharp sky's SH rings below 0), an emitter cannot hold it: the map's negative part
  is a second map (:func:`envmap_parts`), rendered apart with the same paths per pixel and
  subtracted pass by pass (radiance is linear in the light), so Mitsuba renders the SH lighting
  itself, as our reference does; ``clamp_share`` reports how much energy a map clamped at 0
  would have added (on the Duplex's potsdamer lighting 0.5-1.4 %, which showed as a -0.4 %
  brightness bias of our reference against such a map at 4096 paths per pixel).  Mitsuba's
  envmap reads ``u = atan2(x, -z) / 2 pi`` (ours is that + 0.5), columns at texel centres and
  rows at ``v = i / (H - 1)`` (first and last rows on the poles), bilinear in between: the grid
  is made in its convention, and :func:`check_envmap` compares its lookup with the SH at random
  directions every time, so a Mitsuba release that reads maps otherwise is refused.
- **Camera**: the renderer's :class:`~prt.runtime.camera.Camera`; every film sample is moved to
  its pixel's centre (a small sensor, :data:`SENSOR`), so Mitsuba's primary rays are the
  rasteriser's (:meth:`Camera.ray_directions`), and a pixel's value is the mean over its paths
  from that one ray, like the G-buffer's one sample per pixel.
- **Transport**: the ``path`` integrator, ``max_depth = 2 + bounces`` (1: emitters seen
  directly; 2: direct light; one more per bounce), Russian roulette off (it is unbiased but
  adds noise), emitters hidden (the background is black, as the reference's).  The result is
  linear radiance, tone-mapped by the caller with the renderer's own :func:`tonemap`.
- AOVs hold the primary hit's position and shading normal, so a comparison keeps only the
  pixels where both renderers see the same surface point with the same normal.

The variant is chosen at run time (:func:`use_variant`): ``llvm_ad_rgb`` where a libLLVM that
Dr.Jit can use is found (``DRJIT_LIBLLVM_PATH``, or Debian's ``libllvm19``; each candidate is
tried in a child process first, because an unusable LLVM aborts the process), else
``scalar_rgb`` (no dependency, about 10x slower).  Mitsuba is the optional extra
``prt-runtime[mitsuba]``.
"""

from __future__ import annotations

import glob
import hashlib
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from prt.runtime import sh
from prt.runtime.errors import InputError, PRTError
from prt.runtime.files import atomic_save_npz
from prt.runtime.normals import corner_normals

__all__ = ["VARIANTS", "ENVMAP_HEIGHT", "LANES", "use_variant", "band_limited_envmap", "envmap_parts", "check_envmap", "scene_albedos",
           "MitsubaScene", "cached_render"]  # fmt: skip

VARIANTS = ("llvm_ad_rgb", "scalar_rgb")
# Rows of the band-limited env map (columns: twice as many).  Bilinear lookup of a band-3
# function on this grid is within ~1e-4 of its value (measured: 1.2e-4 on values ~3).
ENVMAP_HEIGHT = 256
# Paths per render pass in the LLVM variant (its wavefront holds every lane's state: ~0.4 GB here).
LANES = 1 << 20
# Independent passes of a render, at least: the spread of their means is the noise of a pooled
# mean (pixels of one pass are not independent: the pooled mean brightness of a sphere in a
# white furnace spread 2x further over seeds than per-pixel variances predict).
PASSES = 8
# The env map lookup must match the SH within this share of the map's mean radiance.
ENVMAP_TOLERANCE = 2e-3
# Where Debian / Ubuntu / Fedora put libLLVM (newest first after sorting by version).
_LLVM_GLOBS = ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
               "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*")  # fmt: skip
_PROBE = (
    "import mitsuba as mi\n"
    "mi.set_variant('llvm_ad_rgb')\n"
    "s = mi.load_dict({'type': 'scene', 'e': {'type': 'constant'}, 'b': {'type': 'sphere'},"
    " 'sensor': {'type': 'perspective', 'to_world': mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),"
    " 'film': {'type': 'hdrfilm', 'width': 8, 'height': 8}}, 'integrator': {'type': 'path'}})\n"
    "import numpy as np\n"
    "assert np.isfinite(np.array(mi.render(s, spp=4))).all()\n"
    "print('ok')\n"
)
_CHOSEN: dict = {}  # the variant this process uses: mitsuba's variant is process-wide
_SENSORS: set = set()  # the variants whose pixel-centre sensor is registered


def _import_mitsuba():
    try:
        import mitsuba
    except ImportError:
        raise InputError("--reference mitsuba needs Mitsuba 3: pip install 'prt-runtime[mitsuba]' (or pip install mitsuba)") from None
    return mitsuba


def _llvm_candidates() -> list[str]:
    """libLLVM files on this machine, newest version first; DRJIT_LIBLLVM_PATH first when set."""
    found = {}
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            real = os.path.realpath(path)
            numbers = re.findall(r"(\d+)", Path(real).name)
            if os.path.isfile(real) and numbers:
                found.setdefault(real, int(numbers[0]))
    ordered = sorted(found, key=lambda p: -found[p])
    own = os.environ.get("DRJIT_LIBLLVM_PATH")
    return ([own] if own else []) + [p for p in ordered if p != own]


def _llvm_works(path: str) -> bool:
    """Whether Dr.Jit renders with this libLLVM, tried in a child process (a bad one aborts its process)."""
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": path}
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.SubprocessError):
        return False
    return proc.returncode == 0 and proc.stdout.strip().endswith("ok")


def use_variant(prefer: str = "auto", log=print) -> dict:
    """Set Mitsuba's variant for this process; ``{"variant", "libllvm", "mitsuba"}``.

    Parameters
    ----------
    prefer : {"auto", "llvm_ad_rgb", "scalar_rgb"}
        ``auto``: the LLVM variant where a usable libLLVM is found, else scalar.  Naming the LLVM
        variant without a usable libLLVM is an error.
    """
    if prefer not in ("auto", *VARIANTS):
        raise InputError(f"--mitsuba-variant: expected auto, {' or '.join(VARIANTS)}, got {prefer!r}")
    if _CHOSEN and prefer in ("auto", _CHOSEN["variant"]):
        return dict(_CHOSEN)
    mi = _import_mitsuba()
    library = None
    if prefer in ("auto", "llvm_ad_rgb"):
        library = next((p for p in _llvm_candidates() if _llvm_works(p)), None)
        if library is None and prefer == "llvm_ad_rgb":
            raise InputError("--mitsuba-variant llvm_ad_rgb: no libLLVM that Dr.Jit can use (apt install libllvm19, or set DRJIT_LIBLLVM_PATH)")
    variant = "llvm_ad_rgb" if library else "scalar_rgb"
    if library:
        os.environ["DRJIT_LIBLLVM_PATH"] = library
    mi.set_variant(variant)
    _CHOSEN.clear()
    _CHOSEN.update(variant=variant, libllvm=library, mitsuba=mi.__version__)
    log(f"  mitsuba {mi.__version__}: variant {variant}" + (f" (libLLVM {library})" if library else " (no usable libLLVM found)"))
    return dict(_CHOSEN)


def _mitsuba_grid(height: int) -> np.ndarray:
    """(H, 2H, 3) directions of Mitsuba's envmap texels: ``u = (j + 0.5) / W``, ``v = i / (H - 1)``."""
    width = 2 * height
    theta = np.arange(height) / (height - 1) * np.pi
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    st = np.sin(theta)[:, None]
    out = np.empty((height, width, 3))
    out[..., 0] = st * np.sin(phi)[None, :]
    out[..., 1] = np.cos(theta)[:, None]
    out[..., 2] = -st * np.cos(phi)[None, :]
    return out


def band_limited_envmap(coeffs, height: int = ENVMAP_HEIGHT) -> tuple[np.ndarray, dict]:
    """The radiance of SH lighting on Mitsuba's envmap grid, clamped at 0; ``(image (H, 2H, 3) float32, info)``
    (:func:`envmap_parts`' positive part and info).
    """
    positive, _, info = envmap_parts(coeffs, height)
    return positive, info


def envmap_parts(coeffs, height: int = ENVMAP_HEIGHT) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """The radiance of SH lighting on Mitsuba's envmap grid as two maps of radiance >= 0:
    ``(positive, negative, info)``, ``positive - negative`` = the radiance at every texel (so their
    bilinear lookups differ by the lookup of the SH lighting itself); ``negative`` is None where no
    texel is negative.

    Parameters
    ----------
    coeffs : (n, 3)
        SH lighting (rotation applied), ``n = bands**2``.
    height : int

    Returns
    -------
    positive, negative : (H, 2H, 3) float32 (negative: or None)
    info : dict
        ``height``, ``min_radiance`` (per channel), ``clamped`` (any negative radiance),
        ``clamp_share``: per channel, the energy clamping would remove, ``integral max(0, -L) dw /
        integral L dw`` (the positive part alone is that much brighter in total than the SH
        lighting), ``negative_part``: whether there is a negative map to subtract.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim != 2 or coeffs.shape[1] != 3 or math.isqrt(coeffs.shape[0]) ** 2 != coeffs.shape[0]:
        raise InputError(f"band_limited_envmap: coefficients must be (bands**2, 3), got {coeffs.shape}")
    radiance = sh.evaluate(coeffs, _mitsuba_grid(height))
    # The energy clamping removes, by the exact texel solid angles of a finer grid of our own.
    fine = sh.evaluate(coeffs, sh.envmap_directions(512, 1024))
    weight = sh.texel_solid_angles(512, 1024)[..., None]
    negative = (np.maximum(-fine, 0.0) * weight).sum(axis=(0, 1))
    total = np.sqrt(4.0 * np.pi) * coeffs[0]  # integral of L: only Y_00 has a non-zero mean
    share = np.divide(negative, total, out=np.full(3, np.inf), where=total > 0)
    info = {"height": int(height), "min_radiance": [round(float(v), 6) for v in fine.min(axis=(0, 1))],
            "clamped": bool((fine < 0).any()), "clamp_share": [float(v) for v in share]}  # fmt: skip
    positive = np.ascontiguousarray(np.maximum(radiance, 0.0), dtype=np.float32)
    negative = np.ascontiguousarray(np.maximum(-radiance, 0.0), dtype=np.float32)
    info["negative_part"] = bool(negative.max() > 0)
    return positive, (negative if info["negative_part"] else None), info


def check_envmap(emitter, coeffs, count: int = 256, negative=None) -> float:
    """Mitsuba's lookup of ``emitter`` against the clamped SH radiance at ``count`` random directions;
    with ``negative`` (the negative part's emitter, :func:`envmap_parts`), the lookup of ``emitter``
    minus that of ``negative`` against the SH radiance itself.

    Returns the largest difference as a share of the mean radiance; raises PRTError above
    :data:`ENVMAP_TOLERANCE` (a Mitsuba release that reads env maps differently).
    """
    import drjit as dr
    import mitsuba as mi

    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    truth = sh.evaluate(np.asarray(coeffs, dtype=np.float64), dirs)
    if negative is None:
        truth = np.maximum(truth, 0.0)

    def lookup(light) -> np.ndarray:
        if mi.variant().startswith("scalar"):
            got = []
            for d in dirs:
                si = dr.zeros(mi.SurfaceInteraction3f)
                si.wi = mi.Vector3f(*(-d))
                got.append(np.array(light.eval(si)))
            return np.asarray(got, dtype=np.float64).reshape(count, 3)
        si = dr.zeros(mi.SurfaceInteraction3f, count)
        si.wi = mi.Vector3f(*(-dirs.T))
        return np.asarray(light.eval(si), dtype=np.float64).reshape(3, count).T

    got = lookup(emitter) - (0.0 if negative is None else lookup(negative))
    mean = max(float(np.abs(truth).mean()), 1e-12)
    error = float(np.abs(got - truth).max() / mean)
    if not error <= ENVMAP_TOLERANCE:
        raise PRTError(f"Mitsuba {mi.__version__}: its envmap lookup differs from the SH lighting by {error:.2%} of the mean "
                       f"radiance (allowed {ENVMAP_TOLERANCE:.1%}): this release reads env maps in another convention")  # fmt: skip
    return error


def scene_albedos(manifest) -> dict:
    """``{object: [r, g, b]}``: the diffuse albedo of every object, as the build used it.

    The albedos of the build's bounces (``interreflection.albedos``) where it has them (a bounce
    and the surface seen must agree), else each object's diffuse material, else the scene's.
    """
    from prt.runtime.materials import object_materials

    names = list(manifest.geometry.objects or ["object0"])
    record = ((manifest.raw or {}).get("interreflection") or {}).get("albedos") or {}
    per_object = object_materials(manifest.raw, manifest.geometry.objects, str(manifest.path), root=manifest.root) or {}
    out = {}
    for name in names:
        if name in record:
            out[name] = [float(v) for v in record[name]]
        elif name in per_object and getattr(per_object[name], "albedo", None) is not None:
            out[name] = [float(v) for v in per_object[name].albedo]
        else:
            out[name] = [float(v) for v in manifest.material.albedo]
    return out


def _register_sensor(mi, dr) -> str:
    """Register (once per variant) the sensor that moves every film sample to its pixel's centre."""
    name = f"prt_pixel_centres_{mi.variant()}"
    if name in _SENSORS:
        return name

    class PixelCentres(mi.Sensor):
        """A pinhole camera whose rays pass through pixel centres: ``Camera.ray_directions``'s rays."""

        def __init__(self, props):
            super().__init__(props)
            size = self.film().size()
            self.size = (int(size[0]), int(size[1]))
            self.set_camera(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 1.0, 1.0)

        def set_camera(self, eye, forward, right, up, half_x, half_y):
            # Opaque in the LLVM variant, so one compiled kernel serves every view.
            values = [mi.Vector3f(*map(float, v)) for v in (eye, forward, np.asarray(right) * half_x, np.asarray(up) * half_y)]
            if dr.is_jit_v(mi.Float):
                dr.make_opaque(*values)
            self.eye, self.forward, self.right, self.up = values

        def _ray(self, time, position):
            width, height = self.size
            px = (dr.floor(position.x * width) + 0.5) / width
            py = (dr.floor(position.y * height) + 0.5) / height
            d = dr.normalize(self.forward + (2.0 * px - 1.0) * self.right + (1.0 - 2.0 * py) * self.up)
            return mi.Ray3f(mi.Point3f(self.eye), d, time)

        def sample_ray(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            return self._ray(time, position_sample), mi.Color3f(1.0)

        def sample_ray_differential(self, time, wavelength_sample, position_sample, aperture_sample, active=True):
            return mi.RayDifferential3f(self._ray(time, position_sample)), mi.Color3f(1.0)

        def bbox(self):
            return mi.ScalarBoundingBox3f()

        def to_string(self):
            return "PixelCentres[]"

    mi.register_sensor(name, lambda props: PixelCentres(props))
    _SENSORS.add(name)
    return name


class MitsubaScene:
    """The scene as built, for Mitsuba (see the module docstring); render views with :meth:`render`.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    object_ids : (F,) int
    two_sided : (F,) bool
    albedo : (K, 3) float
        Diffuse albedo of object ``k``.
    coeffs : (n, 3)
        SH lighting (rotation applied).
    bounces : int
        Interreflected bounces: ``max_depth = 2 + bounces``.
    variant : str
        :func:`use_variant`'s ``prefer``.
    """

    def __init__(self, vertices, faces, object_ids, two_sided, albedo, coeffs, bounces: int, *, variant: str = "auto",
                 envmap_height: int = ENVMAP_HEIGHT, log=print):  # fmt: skip
        self.info = use_variant(variant, log=log)
        import drjit as dr
        import mitsuba as mi

        self.mi, self.dr = mi, dr
        vertices = np.asarray(vertices, dtype=np.float32)
        faces = np.asarray(faces, dtype=np.int64)
        object_ids = np.asarray(object_ids, dtype=np.int64)
        two_sided = np.asarray(two_sided, dtype=bool)
        albedo = np.asarray(albedo, dtype=np.float64).reshape(-1, 3)
        if object_ids.max(initial=0) >= len(albedo):
            raise InputError(f"MitsubaScene: object id {int(object_ids.max())} has no albedo ({len(albedo)} given)")
        self.bounces = int(bounces)
        face_normal, corner = corner_normals(vertices, faces)
        keep = np.linalg.norm(face_normal, axis=1) > 0.0  # degenerate faces: no normal, no area
        self.shapes = {}
        for obj in np.unique(object_ids[keep]):
            for side in (False, True):
                chosen = np.flatnonzero(keep & (object_ids == obj) & (two_sided == side))
                if len(chosen):
                    self.shapes[f"object{obj}{'_two_sided' if side else ''}"] = self._mesh(vertices[faces[chosen]], corner[chosen], albedo[obj], side)
        self.envmap, negative, self.envmap_info = envmap_parts(coeffs, envmap_height)
        self.emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(self.envmap)})
        # The negative part, rendered apart and subtracted (module docstring); None where there is none.
        self.negative_emitter = None if negative is None else mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(negative)})
        self.envmap_info["lookup_error"] = check_envmap(self.emitter, coeffs, negative=self.negative_emitter)
        self.sensor_type = _register_sensor(mi, dr)
        self._scenes = {}  # (width, height) -> (scene, sensor)

    def _mesh(self, corners, normals, albedo, two_sided: bool):
        """One Mitsuba mesh of unwelded triangles: corners (F, 3, 3) with their normals (F, 3, 3)."""
        mi = self.mi
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(a) for a in albedo]}}
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": bsdf} if two_sided else bsdf)
        count = len(corners)
        mesh = mi.Mesh("prt", 3 * count, count, props=props, has_vertex_normals=True)
        params = mi.traverse(mesh)
        params["vertex_positions"] = np.ascontiguousarray(corners, dtype=np.float32).ravel()
        params["vertex_normals"] = np.ascontiguousarray(normals, dtype=np.float32).ravel()
        params["faces"] = np.arange(3 * count, dtype=np.uint32)
        params.update()
        return mesh

    def _scene(self, width: int, height: int, negative: bool = False):
        """The scene lit by the map's positive part, or by its negative part (``negative``)."""
        key = (int(width), int(height), bool(negative))
        if key not in self._scenes:
            mi = self.mi
            film = {"type": "hdrfilm", "width": key[0], "height": key[1], "rfilter": {"type": "box"}, "pixel_format": "rgb",
                    "sample_border": False}  # fmt: skip
            path = {"type": "path", "max_depth": 2 + self.bounces, "rr_depth": 2 + self.bounces + 1, "hide_emitters": True}
            scene = mi.load_dict({
                "type": "scene", "emitter": self.negative_emitter if negative else self.emitter, **self.shapes,
                "sensor": {"type": self.sensor_type, "film": film, "sampler": {"type": "independent", "sample_count": 1}},
                "integrator": {"type": "aov", "aovs": "position:position,normal:sh_normal", "path": path},
            })  # fmt: skip
            self._scenes[key] = (scene, scene.sensors()[0])
        return self._scenes[key]

    def render(self, camera, width: int, height: int, spp: int, seed: int = 0, lanes: int = LANES, passes: int = PASSES) -> dict:
        """Path-trace one view at the pixel centres.

        Parameters
        ----------
        camera : prt.runtime.camera.Camera
        width, height : int
        spp : int
            Paths per pixel (rounded up to equal passes).
        seed : int
            Passes use the seeds ``2 ** 16 * seed + pass`` (the negative part's, where there is one,
            ``2 ** 16 * seed + passes + pass``).
        lanes : int
            Paths per pass at most (LLVM variant).
        passes : int
            Independent passes at least (even; more where ``lanes`` needs them).

        Returns
        -------
        dict
            ``radiance`` (H, W, 3) float32 linear (mean of all passes), ``passes`` (P, H, W, 3): each
            pass's image (independent estimates: the noise; each the positive part's render minus
            the negative part's), ``position`` and ``normal`` (H, W, 3):
            the primary hit and its shading normal (as interpolated, not turned to the camera;
            zeros where none), ``spp`` (paths per pixel rendered), ``seconds``.
        """
        passes = max(2, int(passes))
        if spp < passes:
            raise InputError(f"Mitsuba reference: spp must be at least {passes} (one path per pass), got {spp}")
        half_x = math.tan(math.radians(camera.fov_y) / 2.0) * width / height
        for negative in (False, True)[: 1 + (self.negative_emitter is not None)]:
            sensor = self._scene(width, height, negative)[1]
            sensor.set_camera(camera.eye, camera.forward, camera.right, camera.true_up, half_x, half_x * height / width)
        scene = self._scene(width, height)[0]
        if self.dr.is_jit_v(self.mi.Float):
            passes = max(passes, math.ceil(spp * width * height / lanes))
        passes += passes % 2
        per_pass = math.ceil(spp / passes)
        images = np.zeros((passes, height, width, 3), dtype=np.float32)
        position = normal = None
        t0 = time.perf_counter()
        for k in range(passes):
            out = np.asarray(self.mi.render(scene, spp=per_pass, seed=(2**16) * int(seed) + k), dtype=np.float32)
            images[k] = out[..., :3]
            if self.negative_emitter is not None:
                minus = self.mi.render(self._scene(width, height, True)[0], spp=per_pass, seed=(2**16) * int(seed) + passes + k)
                images[k] -= np.asarray(minus, dtype=np.float32)[..., :3]
            if position is None:  # every path of a pixel starts with the same primary ray: one pass tells
                position, normal = out[..., 3:6], out[..., 6:9]
        return {"radiance": images.mean(axis=0, dtype=np.float64).astype(np.float32), "passes": images, "position": position,
                "normal": normal, "spp": passes * per_pass, "seconds": time.perf_counter() - t0}  # fmt: skip


def cached_render(cache: Path | None, tag: str, scene: MitsubaScene, key: str, camera, width: int, height: int, spp: int, seed: int = 0) -> dict:
    """:meth:`MitsubaScene.render`, read from ``cache`` (a folder) when rendered before with the same inputs.

    ``key`` names the scene's content (geometry, albedos, lighting, bounces); the camera, size,
    spp, seed and variant are added here.  ``seconds`` is 0 for a cached render.
    """
    if cache is None:
        return scene.render(camera, width, height, spp, seed)
    parts = [key, camera.eye.tolist(), camera.target.tolist(), camera.up.tolist(), camera.fov_y, width, height, spp, seed,
             scene.info["variant"], scene.info["mitsuba"], "v3"]  # fmt: skip
    digest = hashlib.sha1(repr(parts).encode()).hexdigest()[:12]
    path = Path(cache) / f"{tag}-mitsuba-{width}x{height}-spp{spp}-s{seed}-{digest}.npz"
    if path.is_file():
        with np.load(path) as data:
            return {"radiance": data["radiance"], "passes": data["passes"], "position": data["position"], "normal": data["normal"],
                    "spp": int(data["spp"]), "seconds": 0.0}  # fmt: skip
    result = scene.render(camera, width, height, spp, seed)
    atomic_save_npz(path, radiance=result["radiance"], passes=result["passes"], position=result["position"], normal=result["normal"],
                    spp=np.int64(result["spp"]), seconds=np.float64(result["seconds"]))  # fmt: skip
    return result
