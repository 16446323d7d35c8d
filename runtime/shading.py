"""PRT shading: transfer vectors and SH lighting to outgoing radiance, plus tone mapping.

numpy only.  This module is the reference definition; ``shaders/shading.glsl`` (with
``shaders/sh_basis.glsl``) is its GLSL twin for 4 bands, and the two must give the same image.

Inputs per pixel
----------------
* ``T`` (n = bands**2): transfer vector,
  ``T_i = (1/pi) * integral V(w) max(0, n.w) Y_i(w) dw`` (see :mod:`prt.runtime.sh`), so an
  unoccluded point under constant radiance 1 has ``dot(T, L_c) = 1``.  ``T~(w) = sum_i T_i Y_i(w)``
  is the function it stands for (visibility times cosine over pi).
* ``n``: surface normal; ``v``: direction from the point towards the eye.  Neither needs to be
  unit length.  Callers shading two-sided surfaces flip ``n`` to the side facing the eye first.

Lighting
--------
``L`` (n, 3): SH projection of the environment, one column per RGB channel.  An optional
rotation ``R`` is applied first, ``L <- sh.rotate(L, R)`` (the environment turned by ``R``).
From it, once per lighting change, the *light matrix* (3, n, n)::

    M_c[k, j] = sum_i L[i, c] * G[i, j, k],    G = sh.gaunt(bands)

so that ``M_c @ T`` are the SH coefficients (truncated to ``bands``) of the transferred incident
radiance ``L'_c(w) = L_c(w) * T~(w)``.  ``M_c`` is symmetric because ``G`` is.

Radiance
--------
With ``r = reflect(-v, n) = 2 (n.v) n - v`` (unit ``n``, ``v``; the mirror direction) and
``Lambda_l = sh.phong_lobe(exponent)`` the band factors of the normalised Phong lobe
``(e+1)/(2 pi) max(0, cos)^e``::

    diffuse_c = dot(T, L_c)
    spec_c    = pi * sum_k Lambda_{l(k)} * Y_k(r) * (M_c @ T)_k
    radiance_c = max(0, albedo_c * diffuse_c)                             kind "diffuse"
    radiance_c = max(0, albedo_c * diffuse_c + specular_c * spec_c)       kind "glossy"

Interreflection (``prt-train --bounces``): the transfer is ``4 n`` wide, ``[T, T_ind_R, T_ind_G,
T_ind_B]`` (the "direct+rgb" layout), and the indirect light enters as a diffuse term::

    indirect_c = dot(T_ind_c, L_c)
    radiance_c = max(0, albedo_c * (diffuse_c + indirect_c) [+ specular_c * spec_c])

Glossy receivers take the Phong lobe of the direct light only and the indirect light as if the
surface were diffuse (scaled by its diffuse albedo): the approximation of a lobe that does not
resolve the (smooth, low-frequency) interreflected light; the bounces themselves are diffuse.

``spec_c`` is ``L'_c`` convolved with the lobe and read at ``r`` (Funk-Hecke); the factor ``pi``
undoes the ``1/pi`` inside ``T``, so under a white furnace (``L = 1``) an unoccluded point seen
at normal incidence has ``spec ~ (e+1)/(e+2)``, up to 4-band truncation (exactly 1/2 as
``e -> 0``).  Four SH bands ring below zero near strong lights, hence the clamp at 0.

Display
-------
:func:`tonemap`: non-finite values become 0, then ``x = clip(exposure * radiance, 0, 1e4)``, the
ACES filmic fit of Narkowicz (2015) per channel,
``f(x) = clip(x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), 0, 1)`` (monotone, ``f(0) = 0``,
1 from ``x ~ 7.24``), and the sRGB OETF (:func:`linear_to_srgb`).  :func:`to_srgb8` rounds that
to 8 bits.  ``prt_tonemap`` in ``tonemap.glsl`` is the GLSL twin; its ceiling is
:data:`TONEMAP_MAX`, passed in as the ``#define PRT_TONEMAP_MAX`` of :data:`GLSL_DEFINES`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..shaders import assemble
from . import sh
from .checks import check_finite, finite_array
from .envmap import load_envmap_sh
from .errors import InputError

__all__ = [
    "MATERIAL_KINDS",
    "Lighting",
    "DERING_WINDOW",
    "DERING_AUTO_RINGING",
    "lighting_ringing",
    "Material",
    "compute_light_matrix",
    "diffuse_light_matrix",
    "split_transfer",
    "reflect",
    "shade",
    "shader_uniforms",
    "glsl_source",
    "GLSL_FILES",
    "GLSL_DEFINES",
    "TONEMAP_MAX",
    "tonemap",
    "linear_to_srgb",
    "to_srgb8",
]

MATERIAL_KINDS = ("diffuse", "glossy")
"""Material kinds; the index of each is its ``u_material_kind`` value in ``shading.glsl``."""

# The GLSL twin hard-codes this many bands.
GLSL_BANDS = 4
# Rows shaded per chunk in shade(); bounds the (rows, 3, n) temporaries to a few tens of MB.
_SHADE_CHUNK = 1 << 16
# Tone-mapping input ceiling: the curve is already 1 beyond ~7.3, and x * x stays finite.
TONEMAP_MAX = 1.0e4
# The GLSL twin of this module, in the order prt.shaders.assemble includes it, and the values
# it takes from here (the one definition of each).
GLSL_FILES = ("sh_basis.glsl", "shading.glsl", "tonemap.glsl")
GLSL_DEFINES = {"PRT_TONEMAP_MAX": TONEMAP_MAX}
# ACES filmic fit (Narkowicz 2015): x (a x + b) / (x (c x + d) + e).
_ACES = (2.51, 0.03, 2.43, 0.59, 0.14)


# --------------------------------------------------------------------------- lighting


def compute_light_matrix(coeffs) -> np.ndarray:
    """Light matrices of an SH lighting: multiply a transfer vector by the lighting.

    Parameters
    ----------
    coeffs : array_like, shape (n, 3)
        SH lighting ``L``, one column per channel; ``n = bands**2``.

    Returns
    -------
    ndarray, shape (3, n, n), float64
        ``M[c, k, j] = sum_i L[i, c] * G[i, j, k]`` with ``G = sh.gaunt(bands)``: ``M[c] @ T`` are
        the coefficients of the product of ``L_c`` and the function with coefficients ``T``.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    bands = math.isqrt(coeffs.shape[0])
    return np.einsum("ic,ijk->ckj", coeffs, sh.gaunt(bands))


def _check_sh(coeffs) -> np.ndarray:
    """``coeffs`` as float64 (n, 3) with n a positive square and finite values, else InputError."""
    arr = finite_array(coeffs, "Lighting.sh", shape=(-1, 3))  # finite in float32, the precision of the shading
    n = arr.shape[0]
    if n < 1 or math.isqrt(n) ** 2 != n:
        raise InputError(f"Lighting.sh must have shape (bands**2, 3), got {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Lighting:
    """SH lighting ready for shading: coefficients and their light matrices.

    Parameters
    ----------
    sh : array_like, shape (n, 3)
        SH coefficients per RGB channel, already rotated; ``n = bands**2``.

    Attributes
    ----------
    sh : ndarray, shape (n, 3), float64, read-only
    light_matrix : ndarray, shape (3, n, n), float64, read-only
        :func:`compute_light_matrix` of ``sh``, computed once here.

    Raises
    ------
    InputError
        (a ValueError) naming ``sh`` if it has the wrong shape or non-finite values.
    """

    sh: np.ndarray
    light_matrix: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        coeffs = _check_sh(self.sh)
        matrix = compute_light_matrix(coeffs)
        check_finite(matrix, "Lighting.sh: its light matrix")  # sums of products can overflow float32
        coeffs.setflags(write=False)
        matrix.setflags(write=False)
        # Frozen dataclass: the validated copies replace the fields through object.__setattr__.
        object.__setattr__(self, "sh", coeffs)
        object.__setattr__(self, "light_matrix", matrix)

    @property
    def bands(self) -> int:
        """Number of SH bands."""
        return math.isqrt(self.sh.shape[0])

    @classmethod
    def from_sh(cls, coeffs, rotation=None, window=None) -> "Lighting":
        """Lighting from SH coefficients, optionally rotated and deringed.

        Parameters
        ----------
        coeffs : array_like, shape (n, 3)
            SH projection of the environment (``sh.project_envmap``).
        rotation : array_like, shape (3, 3), optional
            Rotation of the environment: what was at direction ``w`` is now at ``rotation @ w``.
        window : (kind, width) or "auto", optional
            Deringing window on the lighting's bands (``sh.window``, Sloan 2008), e.g.
            ``("hanning", 6.0)``; ``"auto"``: :data:`DERING_WINDOW` where the lighting rings
            strongly (:func:`lighting_ringing` > :data:`DERING_AUTO_RINGING`), else none; None:
            none.  It commutes with the rotation.

        Returns
        -------
        Lighting

        Raises
        ------
        InputError
            Naming ``sh`` or ``rotation``.
        """
        coeffs = _check_sh(coeffs)
        if rotation is not None:
            try:
                coeffs = sh.rotate(coeffs, rotation)
            except (TypeError, ValueError) as exc:
                raise InputError(f"Lighting rotation: {' '.join(str(exc).split())[:200]}") from None
        if isinstance(window, str) and window == "auto":
            window = DERING_WINDOW if lighting_ringing(coeffs) > DERING_AUTO_RINGING else None
        if window is not None:
            try:
                kind, width = window
                coeffs = sh.apply_window(coeffs, sh.window(math.isqrt(coeffs.shape[0]), kind, width))
            except (TypeError, ValueError) as exc:
                raise InputError(f"Lighting window: expected (kind, width) with kind 'hanning' or 'lanczos' and width > 0; "
                                 f"{' '.join(str(exc).split())[:160]}") from None  # fmt: skip
        return cls(coeffs)

    @classmethod
    def from_envmap(cls, path, rotation=None, bands: int = 4, window=None) -> "Lighting":
        """Lighting from an equirectangular ``.hdr`` / ``.exr`` env map.

        Parameters
        ----------
        path : str or os.PathLike
        rotation : array_like, shape (3, 3), optional
            As in :meth:`from_sh`.
        bands : int
            Number of SH bands (4 for the GLSL path).
        window : (kind, width), optional
            As in :meth:`from_sh`.

        Returns
        -------
        Lighting

        Raises
        ------
        EnvmapError
            If the file cannot be read (names the file).
        InputError
            Naming ``rotation``.
        """
        return cls.from_sh(load_envmap_sh(path, bands), rotation, window)


# Issue 12 (studies/dering.py, README "Deringing"): against the env map itself, Hanning at
# width 6 takes the glossy (exponent 32) black-clamped pixels under ``studio`` from 4.5 % to 0 and
# its PSNR from 15.7 to 19.4 dB, while it costs 3-10 dB where the light barely rings (potsdamer).
DERING_WINDOW = ("hanning", 6.0)
DERING_AUTO_RINGING = 1.0  # "auto" windows a light whose 4-band reconstruction dips below -1 x its mean


def lighting_ringing(coeffs) -> float:
    """How far the SH lighting's reconstruction goes negative: max over channels of -min / mean (0: never).

    ``coeffs`` (n, 3); evaluated on a 32 x 64 grid of directions.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    values = sh.evaluate(coeffs, sh.envmap_directions(32, 64).reshape(-1, 3))
    weights = sh.texel_solid_angles(32, 64).reshape(-1, 1)
    mean = np.maximum((values * weights).sum(axis=0) / weights.sum(), 1e-12)
    return float(np.max(np.maximum(-values.min(axis=0), 0.0) / mean))


# --------------------------------------------------------------------------- material


def _check_rgb(name: str, value) -> tuple[float, float, float]:
    """``value`` (scalar or 3 values, finite, >= 0) as a tuple of 3 floats, else InputError."""
    arr = finite_array(value, f"Material.{name}", minimum=0.0)  # finite in float32, the shading's precision
    try:
        arr = np.broadcast_to(arr, (3,))
    except ValueError:
        raise InputError(f"Material.{name} must be a number or 3 numbers, got shape {arr.shape}") from None
    return tuple(float(x) for x in arr)


@dataclass(frozen=True)
class Material:
    """Surface material.

    Parameters
    ----------
    kind : {"diffuse", "glossy"}
        ``diffuse`` ignores ``specular`` and ``exponent``.
    albedo : float or sequence of 3 floats
        Diffuse reflectance per RGB channel, >= 0 (<= 1 conserves energy).
    specular : float or sequence of 3 floats
        Scale of the normalised Phong lobe per channel, >= 0.  The default 0.04 is the
        normal-incidence reflectance of a typical dielectric (index ~1.5); there is no Fresnel
        term, so raise it for a visibly glossier look.
    exponent : float
        Phong exponent, > 0.  Four SH bands cannot hold a lobe much sharper than ~8-16: beyond
        that the band factors approach 1 and the highlight stops getting sharper.

    Raises
    ------
    InputError
        (a ValueError) naming the field at fault.
    """

    kind: str = "diffuse"
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    specular: tuple[float, float, float] = (0.04, 0.04, 0.04)
    exponent: float = 8.0

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or self.kind not in MATERIAL_KINDS:
            raise InputError(f"Material.kind must be one of {MATERIAL_KINDS}, got {self.kind!r}")
        object.__setattr__(self, "albedo", _check_rgb("albedo", self.albedo))
        object.__setattr__(self, "specular", _check_rgb("specular", self.specular))
        exponent = float(finite_array(self.exponent, "Material.exponent", ()))
        if not exponent > 0:
            raise InputError(f"Material.exponent must be finite and > 0, got {self.exponent!r}")
        object.__setattr__(self, "exponent", exponent)

    def lobe_band_factors(self, bands: int = 4) -> np.ndarray:
        """Phong-lobe band factors ``Lambda_l``, shape (bands,), float64 (``sh.phong_lobe``)."""
        return sh.phong_lobe(self.exponent, bands)


# --------------------------------------------------------------------------- shading


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, 3) scaled to unit length; zero rows stay zero (GLSL twin: prt_unit)."""
    norm = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def reflect(view_dirs, normals) -> np.ndarray:
    """Mirror directions ``r = reflect(-v, n) = 2 (n.v) n - v``.

    Parameters
    ----------
    view_dirs : array_like, shape (N, 3)
        Directions from the point towards the eye (normalised here).
    normals : array_like, shape (N, 3)
        Normals (normalised here).

    Returns
    -------
    ndarray, shape (N, 3), float64
        Unit mirror directions.  A zero input vector counts as zero (as in the GLSL), so a
        zero normal gives ``-v``.
    """
    v = _unit(np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3))
    n = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    return 2.0 * np.einsum("ij,ij->i", n, v)[:, None] * n - v


def _as_rows(name: str, value, width: int, lead: tuple[int, ...] | None) -> np.ndarray:
    """``value`` as float64 (rows, width) with leading shape ``lead`` (if given), else InputError."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim < 1 or arr.shape[-1] != width or (lead is not None and arr.shape[:-1] != lead):
        want = f"{lead + (width,)}" if lead is not None else f"(..., {width})"
        raise InputError(f"shade(): {name} must have shape {want}, got {arr.shape}")
    return arr.reshape(-1, width)


def split_transfer(t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Rows of transfer ``(M, n)`` or ``(M, 4 n)`` (interreflection) as (direct (M, n), indirect
    (M, 3, n) or None)."""
    if t.shape[1] == n:
        return t, None
    return t[:, :n], t[:, n:].reshape(len(t), 3, n)


def _stacked_light(lighting: Lighting) -> np.ndarray:
    """(4 n, 3) float64: ``[L; L_R e_R; L_G e_G; L_B e_B]``, so ``T @ it`` = ``dot(T, L_c) + dot(T_ind_c, L_c)``."""
    n = lighting.sh.shape[0]
    out = np.zeros((4 * n, 3))
    out[:n] = lighting.sh
    for c in range(3):
        out[n * (c + 1) : n * (c + 2), c] = lighting.sh[:, c]
    return out


def diffuse_light_matrix(lighting: Lighting, albedo, width: int) -> np.ndarray:
    """(width, 3) float32 ``A`` with ``T @ A`` = the diffuse radiance ``albedo_c (dot(T, L_c) +
    dot(T_ind_c, L_c))`` of transfer rows ``T`` of ``width`` = n or 4 n (before the clamp at 0)."""
    albedo = np.asarray(albedo, dtype=np.float64)
    if width == lighting.sh.shape[0]:
        return (lighting.sh * albedo).astype(np.float32)
    return (_stacked_light(lighting) * albedo).astype(np.float32)


def shade(transfer, normals, view_dirs, lighting: Lighting, material: Material) -> np.ndarray:
    """Outgoing radiance of shaded points (numpy reference; see the module docstring).

    Parameters
    ----------
    transfer : array_like, shape (..., n) or (..., 4 n)
        Transfer vectors ``T``, ``n = lighting.bands**2``; ``4 n``: direct, then indirect R, G, B
        (interreflection, see the module docstring).
    normals : array_like, shape (..., 3)
        Normals (normalised here), facing the eye for two-sided surfaces.
    view_dirs : array_like, shape (..., 3)
        Directions from each point towards the eye (normalised here).
    lighting : Lighting
    material : Material

    Returns
    -------
    ndarray, shape (..., 3), float32
        Linear RGB radiance, >= 0.  Computed in float64.

    Raises
    ------
    InputError
        Naming ``transfer``, ``normals`` or ``view_dirs`` if a shape does not fit.
    """
    n_coeffs = lighting.sh.shape[0]
    lead = np.shape(transfer)[:-1]
    width = 4 * n_coeffs if np.shape(transfer)[-1:] == (4 * n_coeffs,) else n_coeffs
    t_all = _as_rows("transfer", transfer, width, None)
    n_all = _as_rows("normals", normals, 3, lead)
    v_all = _as_rows("view_dirs", view_dirs, 3, lead)

    albedo = np.asarray(material.albedo)
    specular = np.asarray(material.specular)
    glossy = material.kind == "glossy"
    stacked_light = lighting.sh if width == n_coeffs else _stacked_light(lighting)
    if glossy:
        lobe = sh.band_factors_to_coeff_scale(material.lobe_band_factors(lighting.bands))
        # (n, 3n): column c*n + k is row k of M_c, so t @ it gives every (M_c t)_k at once.
        stacked = lighting.light_matrix.reshape(3 * n_coeffs, n_coeffs).T

    out = np.empty((t_all.shape[0], 3), dtype=np.float32)
    for start in range(0, t_all.shape[0], _SHADE_CHUNK):
        rows = slice(start, start + _SHADE_CHUNK)
        t = t_all[rows]
        # dot(T, L_c), plus dot(T_ind_c, L_c) with interreflection (a diffuse term, also for glossy
        # receivers): one product with the stacked lighting.
        radiance = albedo * (t @ stacked_light)
        if width != n_coeffs:
            t = np.ascontiguousarray(t[:, :n_coeffs])  # the direct part (a strided view is slow in BLAS)
        if glossy:
            r = reflect(v_all[rows], n_all[rows])
            lobe_at_r = sh.basis(r, lighting.bands) * lobe
            transferred = (t @ stacked).reshape(-1, 3, n_coeffs)
            spec = np.pi * np.einsum("pck,pk->pc", transferred, lobe_at_r)
            radiance += specular * spec
        out[rows] = np.maximum(radiance, 0.0)
    return out.reshape(lead + (3,))


def shader_uniforms(lighting: Lighting, material: Material) -> dict[str, np.ndarray]:
    """Uniform values for ``shaders/shading.glsl``.

    Parameters
    ----------
    lighting : Lighting
        Must have 4 bands (the GLSL is written for 4).
    material : Material

    Returns
    -------
    dict of str to ndarray
        Every uniform of ``shading.glsl``, each a C-contiguous array whose bytes are exactly
        what GL expects, so ``program[name].write(value.tobytes())`` sets it:

        ``u_light``  (16, 3) float32
            ``L[i, :]`` (rotated).
        ``u_light_matrix``  (48, 16) float32
            Element ``b = 16*c + 4*bi + bj`` is the block
            ``M_c[4*bi : 4*bi+4, 4*bj : 4*bj+4]`` in column-major order (a GLSL ``mat4``).
        ``u_lobe``  (4, 4) float32
            ``Lambda_l(i)`` of coefficient ``i`` at ``[i // 4, i % 4]``.
        ``u_albedo``, ``u_specular``  (3,) float32
        ``u_material_kind``  () int32
            Index in :data:`MATERIAL_KINDS` (0 diffuse, 1 glossy).

    Raises
    ------
    InputError
        If ``lighting`` does not have 4 bands.
    """
    if lighting.bands != GLSL_BANDS:
        raise InputError(f"shading.glsl needs Lighting with {GLSL_BANDS} bands, got {lighting.bands}")
    blocks = lighting.light_matrix.reshape(3, 4, 4, 4, 4)  # [c, bi, row, bj, col]
    # Order (c, bi, bj, col, row): each block's 16 values column after column, as GLSL reads them.
    column_major = blocks.transpose(0, 1, 3, 4, 2).reshape(48, 16)
    lobe = sh.band_factors_to_coeff_scale(material.lobe_band_factors(GLSL_BANDS)).reshape(4, 4)
    return {
        "u_light": np.ascontiguousarray(lighting.sh, dtype=np.float32),
        "u_light_matrix": np.ascontiguousarray(column_major, dtype=np.float32),
        "u_lobe": np.ascontiguousarray(lobe, dtype=np.float32),
        "u_albedo": np.asarray(material.albedo, dtype=np.float32),
        "u_specular": np.asarray(material.specular, dtype=np.float32),
        "u_material_kind": np.asarray(MATERIAL_KINDS.index(material.kind), dtype=np.int32),
    }


def glsl_source() -> str:
    """The GLSL twin (:data:`GLSL_FILES` with :data:`GLSL_DEFINES`), to paste after a ``#version`` line."""
    return assemble(*GLSL_FILES, defines=GLSL_DEFINES, version=None)


# --------------------------------------------------------------------------- display


def linear_to_srgb(x) -> np.ndarray:
    """sRGB OETF (IEC 61966-2-1) of linear values clipped to [0, 1].

    Parameters
    ----------
    x : array_like, any shape

    Returns
    -------
    ndarray, same shape, float64
        ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x**(1/2.4) - 0.055``; in [0, 1].
    """
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def tonemap(radiance, exposure: float = 1.0) -> np.ndarray:
    """Map linear radiance to display values (see the module docstring).

    Parameters
    ----------
    radiance : array_like, shape (..., 3)
        Linear RGB, e.g. an (H, W, 3) image from :func:`shade`.
    exposure : float
        Multiplier applied first, finite and >= 0.

    Returns
    -------
    ndarray, same shape, float32
        sRGB-encoded values in [0, 1]; non-finite inputs give 0.

    Raises
    ------
    InputError
        Naming ``exposure``.
    """
    exposure = float(exposure)
    if not (math.isfinite(exposure) and exposure >= 0):
        raise InputError(f"tonemap(): exposure must be finite and >= 0, got {exposure!r}")
    x = np.asarray(radiance, dtype=np.float64)
    x = np.clip(np.where(np.isfinite(x), x, 0.0) * exposure, 0.0, TONEMAP_MAX)
    a, b, c, d, e = _ACES
    mapped = np.clip(x * (a * x + b) / (x * (c * x + d) + e), 0.0, 1.0)
    return linear_to_srgb(mapped).astype(np.float32)


def to_srgb8(radiance, exposure: float = 1.0) -> np.ndarray:
    """:func:`tonemap` rounded to 8 bits.

    Parameters
    ----------
    radiance : array_like, shape (..., 3)
    exposure : float

    Returns
    -------
    ndarray, same shape, uint8
    """
    return np.rint(tonemap(radiance, exposure) * 255.0).astype(np.uint8)
