"""Real spherical harmonics (SH): basis, env-map projection, rotation, Gaunt tensor, kernels.

numpy only.  Every function in this module follows the conventions below.

Basis
-----
* Real, orthonormal SH: ``integral Y_i Y_j dw = delta_ij`` over the unit sphere.
* Flat index ``i = l*(l+1) + m`` with ``-l <= m <= l``; ``bands`` is the number of bands
  ``l = 0 .. bands-1`` and there are ``bands**2`` coefficients (default 4 -> 16).
* Polar axis +z, ``cos(theta) = z``, ``phi = atan2(y, x)``.
* No Condon-Shortley phase, so the first band is ``Y_{1,-1} = c*y``, ``Y_{1,0} = c*z``,
  ``Y_{1,1} = c*x`` with ``c = sqrt(3/(4*pi))``.  In general, with ``P_l^m`` the associated
  Legendre function *without* the ``(-1)^m`` factor and
  ``K_lm = sqrt((2l+1)/(4*pi) * (l-m)!/(l+m)!)``::

      Y_l0  = K_l0 * P_l(cos theta)
      Y_lm  = sqrt(2) * K_lm * cos(m*phi)   * P_l^m(cos theta)     (m > 0)
      Y_l-m = sqrt(2) * K_lm * sin(m*phi)   * P_l^m(cos theta)     (m > 0)

Environment maps (equirectangular, latitude-longitude)
-----------------------------------------------------
An image ``(H, W, 3)`` with row 0 at the top.  The texel at (row r, column c) has its centre at
``v = (r + 0.5)/H``, ``u = (c + 0.5)/W``.  Scene up is +Y; ``theta_y = v*pi`` is the angle from
+Y and ``phi = (u - 0.5)*2*pi``; the direction is::

    (sin(theta_y)*sin(phi), cos(theta_y), -sin(theta_y)*cos(phi))

so the image centre looks along -Z, the left and right edges along +Z, ``u = 0.75`` along +X
and ``u = 0.25`` along -X.  The SH basis itself still uses +z as its polar axis; the env map
only defines which direction each texel is.

Rotation
--------
``rotate(c, R)`` returns the coefficients of ``g(w) = f(R^T w)``, i.e. the function ``f``
carried along by the rotation ``R`` (what was at direction ``w0`` is now at ``R w0``).

Transfer normalisation (project-wide)
-------------------------------------
Diffuse transfer vectors include the ``1/pi`` of the Lambertian BRDF:
``T_i = (1/pi) * integral V(w) max(0, n.w) Y_i(w) dw``.  Outgoing diffuse radiance is then
``albedo * dot(T, L)`` with ``L = project_envmap(env)``.  For a constant environment of radiance
1 (``L_00 = sqrt(4*pi)``, all else 0) and an unoccluded point, ``dot(T, L) = 1`` exactly
(the white-furnace test: the diffuse result equals the albedo).

Convolution (Funk-Hecke)
------------------------
Convolving ``f`` with a kernel ``h`` that is rotationally symmetric about +z (zonal
coefficients ``h_l``) multiplies every ``f_lm`` by ``Lambda_l = sqrt(4*pi/(2l+1)) * h_l``.
``clamped_cosine``, ``phong_lobe`` and ``window`` return per-band quantities (length
``bands``); ``band_factors_to_coeff_scale`` expands band factors to all ``bands**2`` slots.
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = [
    "basis",
    "envmap_directions",
    "direction_to_equirect_uv",
    "texel_solid_angles",
    "project_envmap",
    "evaluate",
    "rotation_matrices",
    "rotate",
    "gaunt",
    "clamped_cosine",
    "unshadowed_transfer",
    "unshadowed_coeff_scale",
    "unshadowed_quadratic",
    "QUADRATIC_TERMS",
    "zonal_to_band_factors",
    "phong_lobe",
    "band_factors_to_coeff_scale",
    "window",
    "apply_window",
    "white_furnace_transfer",
]

# Tolerance for accepting a matrix as a rotation (orthonormality and determinant).
_ROTATION_TOL = 1e-4
# Upper bound on (texels x coefficients) evaluated at once by project_envmap, to bound memory.
_PROJECT_CHUNK = 1 << 22
# Number of (direction x coefficient) values basis() computes per chunk, sized for the L2 cache.
_BASIS_CHUNK = 1 << 18
# Rotations per chunk in rotation_matrices(), for the same reason.
_ROTATION_CHUNK = 4096


# --------------------------------------------------------------------------- helpers


def _check_bands(bands: int) -> int:
    """Return ``bands`` as an int, raising ValueError unless it is a positive integer."""
    if isinstance(bands, bool) or int(bands) != bands or bands < 1:
        raise ValueError(f"bands must be a positive integer, got {bands!r}")
    return int(bands)


def _bands_from_count(n: int) -> int:
    """Number of bands of a coefficient vector of length ``n`` (must be a perfect square)."""
    bands = math.isqrt(int(n))
    if n < 1 or bands * bands != n:
        raise ValueError(f"number of SH coefficients must be a positive square, got {n}")
    return bands


def _legendre_moments(exponent: float, bands: int) -> np.ndarray:
    """Half-range moments ``I_l = integral_0^1 z**exponent * P_l(z) dz`` for l < bands.

    Uses the exact recurrence ``I_l = (n - l + 2) / (n + l + 1) * I_{l-2}`` with
    ``I_0 = 1/(n+1)`` and ``I_1 = 1/(n+2)``, valid for real ``n > -1``.  It only multiplies
    positive-denominator ratios, so it stays accurate for large exponents.

    Returns
    -------
    ndarray, shape (bands,), float64
    """
    n = float(exponent)
    moments = np.zeros(bands)
    moments[0] = 1.0 / (n + 1.0)
    if bands > 1:
        moments[1] = 1.0 / (n + 2.0)
    for l in range(2, bands):
        moments[l] = (n - l + 2.0) / (n + l + 1.0) * moments[l - 2]
    return moments


# --------------------------------------------------------------------------- basis


def basis(dirs, bands: int = 4) -> np.ndarray:
    """Evaluate all real SH basis functions at the given directions.

    Parameters
    ----------
    dirs : array_like, shape (..., 3)
        Directions; they are normalised here.  Zero vectors are treated as +z so the result
        stays finite.
    bands : int
        Number of bands (``bands**2`` functions).

    Returns
    -------
    ndarray, shape (..., bands**2)
        ``Y_i(dirs)``; float32 if ``dirs`` is float32, float64 otherwise.

    Notes
    -----
    Uses the normalised associated-Legendre recurrence in cartesian form: ``Y_lm`` is
    ``N_lm(z) * Re/Im((x + i y)**m)`` where ``N_lm`` absorbs ``K_lm`` and the ``sin(theta)**m``
    factor has moved into the complex power, so no trigonometric functions are needed.
    """
    bands = _check_bands(bands)
    dirs = np.asarray(dirs)
    if dirs.shape[-1:] != (3,):
        raise ValueError(f"dirs must have shape (..., 3), got {dirs.shape}")
    dtype = np.float32 if dirs.dtype == np.float32 else np.float64
    lead = dirs.shape[:-1]
    d = dirs.reshape(-1, 3).astype(dtype, copy=False)
    n_coeffs = bands * bands
    out = np.empty((d.shape[0], n_coeffs), dtype=dtype)
    # Chunks keep the per-function temporaries in cache; only the output is large.
    step = max(1, _BASIS_CHUNK // n_coeffs)
    for start in range(0, d.shape[0], step):
        chunk = d[start : start + step]
        out[start : start + step] = _basis_rows(*_unit_xyz(chunk), bands).T
    return out.reshape(lead + (n_coeffs,))


def _unit_xyz(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised x, y, z columns of directions ``d`` (N, 3); zero vectors become +z."""
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    zero = norm == 0
    inv = np.divide(1.0, norm, out=np.zeros_like(norm), where=~zero)
    x = d[:, 0] * inv
    y = d[:, 1] * inv
    z = d[:, 2] * inv
    if zero.any():
        z[zero] = 1.0
    return x, y, z


def _basis_rows(x: np.ndarray, y: np.ndarray, z: np.ndarray, bands: int) -> np.ndarray:
    """SH basis of unit directions given as columns, one contiguous row per function.

    Parameters
    ----------
    x, y, z : ndarray, shape (N,)
        Components of unit vectors (all of one float dtype).
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands**2, N)
        Row ``i`` holds ``Y_i``.
    """
    out = np.empty((bands * bands, x.shape[0]), dtype=x.dtype)
    sqrt2 = math.sqrt(2.0)
    cos_m = np.ones_like(x)  # Re((x + iy)^m)
    sin_m = np.zeros_like(x)  # Im((x + iy)^m)
    p_mm = 1.0 / math.sqrt(4.0 * math.pi)  # N_mm is a constant: sin(theta)^m lives in cos_m/sin_m
    for m in range(bands):
        if m > 0:
            cos_m, sin_m = x * cos_m - y * sin_m, x * sin_m + y * cos_m
            p_mm *= math.sqrt((2.0 * m + 1.0) / (2.0 * m))
            cos_scaled, sin_scaled = sqrt2 * cos_m, sqrt2 * sin_m
        # Walk up in l for this m with N_{l,m}(z): N_mm, N_{m+1,m} = sqrt(2m+3) z N_mm, ...
        p_prev = None
        p_cur = p_mm
        for l in range(m, bands):
            if l == m + 1:
                p_prev, p_cur = p_cur, (math.sqrt(2.0 * m + 3.0) * p_mm) * z
            elif l > m + 1:
                a = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
                b = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
                p_prev, p_cur = p_cur, a * (z * p_cur - b * p_prev)
            centre = l * (l + 1)
            if m == 0:
                out[centre] = p_cur
            else:
                np.multiply(cos_scaled, p_cur, out=out[centre + m])
                np.multiply(sin_scaled, p_cur, out=out[centre - m])
    return out


def evaluate(coeffs, dirs) -> np.ndarray:
    """Reconstruct an SH-expanded function at the given directions.

    Parameters
    ----------
    coeffs : array_like, shape (bands**2, C) or (bands**2,)
        SH coefficients; ``bands`` is inferred from the first dimension.
    dirs : array_like, shape (..., 3)
        Directions (normalised inside).

    Returns
    -------
    ndarray, shape (..., C) or (...)
        ``sum_i coeffs[i] * Y_i(dirs)``.
    """
    coeffs = np.asarray(coeffs)
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"coeffs must have shape (n,) or (n, C), got {coeffs.shape}")
    bands = _bands_from_count(coeffs.shape[0])
    return basis(dirs, bands) @ coeffs


# --------------------------------------------------------------------------- env maps


def envmap_directions(height: int, width: int) -> np.ndarray:
    """Unit directions of the texel centres of an equirectangular env map.

    Parameters
    ----------
    height, width : int
        Image size in texels.

    Returns
    -------
    ndarray, shape (height, width, 3), float64
        Direction of texel (row, col); see the module docstring for the convention.
    """
    if height < 1 or width < 1:
        raise ValueError(f"env map size must be positive, got {height}x{width}")
    return _envmap_rows(height, width, 0, height)


def direction_to_equirect_uv(dirs) -> np.ndarray:
    """Equirectangular texture coordinates of directions (inverse of ``envmap_directions``).

    Parameters
    ----------
    dirs : array_like, shape (..., 3)
        Directions (normalised inside).

    Returns
    -------
    ndarray, shape (..., 2), float64
        ``(u, v)`` with ``u`` in [0, 1) (wrapping horizontally) and ``v`` in [0, 1], v = 0 at +Y.
    """
    d = np.asarray(dirs, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"dirs must have shape (..., 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=-1)
    y = np.divide(d[..., 1], norm, out=np.ones_like(norm), where=norm > 0)
    theta = np.arccos(np.clip(y, -1.0, 1.0))
    phi = np.arctan2(d[..., 0], -d[..., 2])
    u = np.mod(phi / (2.0 * np.pi) + 0.5, 1.0)
    return np.stack([u, theta / np.pi], axis=-1)


def texel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle of each equirectangular texel.

    Parameters
    ----------
    height, width : int
        Image size in texels.

    Returns
    -------
    ndarray, shape (height, width), float64
        ``(2*pi/width) * (cos(theta_top) - cos(theta_bottom))`` per texel; sums to ``4*pi``.
    """
    if height < 1 or width < 1:
        raise ValueError(f"env map size must be positive, got {height}x{width}")
    return np.repeat(_row_solid_angles(height, width)[:, None], width, axis=1)


def project_envmap(image, bands: int = 4) -> np.ndarray:
    """Project an equirectangular env map onto the SH basis.

    Parameters
    ----------
    image : array_like, shape (H, W, 3)
        Linear radiance, row 0 at the top (see the module docstring).
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands**2, 3), float64
        ``sum_texels radiance * Y_i(texel centre) * texel solid angle`` per colour channel.

    Raises
    ------
    ValueError
        If the shape is not (H, W, 3) or the image holds NaN or Inf.
    """
    bands = _check_bands(bands)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"env map image must have shape (H, W, 3), got {img.shape}")
    if not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise ValueError(f"env map image must be real-valued, got dtype {img.dtype}")
    img = img.astype(np.float64, copy=False)
    if not np.isfinite(img).all():
        raise ValueError("env map image contains NaN or Inf values")

    height, width = img.shape[:2]
    # Solid angle is constant along a row, so weight rows once and then project in row chunks.
    row_weight = _row_solid_angles(height, width)
    rows_per_chunk = max(1, _PROJECT_CHUNK // (width * bands * bands))
    coeffs = np.zeros((bands * bands, 3))
    for start in range(0, height, rows_per_chunk):
        stop = min(height, start + rows_per_chunk)
        dirs = _envmap_rows(height, width, start, stop)
        ylm = basis(dirs.reshape(-1, 3), bands)
        weighted = (img[start:stop] * row_weight[start:stop, None, None]).reshape(-1, 3)
        coeffs += ylm.T @ weighted
    return coeffs


def _row_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle of one texel in each row of a (height, width) env map, shape (height,)."""
    edges = np.cos(np.arange(height + 1) / height * np.pi)
    return (edges[:-1] - edges[1:]) * (2.0 * np.pi / width)


def _envmap_rows(height: int, width: int, start: int, stop: int) -> np.ndarray:
    """Texel-centre directions of rows ``start:stop`` of a (height, width) env map, (rows, W, 3)."""
    theta = (np.arange(start, stop) + 0.5) / height * np.pi
    phi = ((np.arange(width) + 0.5) / width - 0.5) * 2.0 * np.pi
    sin_t = np.sin(theta)[:, None]
    out = np.empty((stop - start, width, 3))
    out[..., 0] = sin_t * np.sin(phi)[None, :]
    out[..., 1] = np.cos(theta)[:, None]
    out[..., 2] = -sin_t * np.cos(phi)[None, :]
    return out


# --------------------------------------------------------------------------- rotation


def _check_rotations(R) -> np.ndarray:
    """Return ``R`` as float64 (..., 3, 3), raising ValueError unless every matrix is a rotation."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {R.shape}")
    if not np.isfinite(R).all():
        raise ValueError("rotation matrix contains NaN or Inf values")
    gram = np.swapaxes(R, -1, -2) @ R
    ortho_err = np.abs(gram - np.eye(3)).max(axis=(-2, -1)) if R.size else np.zeros(0)
    det_err = np.abs(np.linalg.det(R) - 1.0) if R.size else np.zeros(0)
    if np.any(ortho_err > _ROTATION_TOL) or np.any(det_err > _ROTATION_TOL):
        raise ValueError(
            "matrix is not a rotation (needs R^T R = I and det R = +1 within "
            f"{_ROTATION_TOL}; worst orthonormality error {float(np.max(ortho_err)):.3g}, "
            f"worst determinant error {float(np.max(det_err)):.3g})"
        )
    return R


@functools.lru_cache(maxsize=None)
def _rotation_samples(bands: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Fixed sample directions per band and the inverses of their band-l basis matrices.

    For band l we use 2l+1 directions ``w_k`` whose matrix ``A_l[j, k] = Y_lj(w_k)`` is well
    conditioned (best of several deterministic random draws).

    Returns
    -------
    dirs : ndarray, shape (bands**2, 3)
        The directions of all bands, band l occupying rows ``l**2 : (l+1)**2``.
    inverses : tuple of ndarray, shapes (2l+1, 2l+1)
        ``inv(A_l)`` for l = 0 .. bands-1.
    """
    rng = np.random.default_rng(20240601)
    all_dirs = []
    inverses = []
    for l in range(bands):
        k = 2 * l + 1
        best = None
        for _ in range(32):
            cand = rng.normal(size=(k, 3))
            cand /= np.linalg.norm(cand, axis=1, keepdims=True)
            a = basis(cand, l + 1)[:, l * l :].T
            cond = np.linalg.cond(a)
            if best is None or cond < best[0]:
                best = (cond, cand, a)
        all_dirs.append(best[1])
        inverses.append(np.linalg.inv(best[2]))
    dirs = np.concatenate(all_dirs, axis=0)
    dirs.setflags(write=False)
    for inv in inverses:
        inv.setflags(write=False)
    return dirs, tuple(inverses)


def rotation_matrices(R, bands: int = 4) -> np.ndarray:
    """SH rotation matrices for a batch of 3D rotations.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Rotation matrices (orthonormal, det +1, within 1e-4).
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (..., bands**2, bands**2), float64
        Block-diagonal ``M`` such that ``M @ c`` are the coefficients of ``g(w) = f(R^T w)``
        when ``c`` are those of ``f``.

    Raises
    ------
    ValueError
        If any matrix is not a rotation.

    Notes
    -----
    Each band is invariant under rotation: ``Y_l(R^T w) = D_l Y_l(w)`` for an orthogonal
    ``D_l``, and the block is ``M_l = D_l^T``.  Sampling ``2l+1`` fixed directions ``w_k`` with
    ``A_l[j, k] = Y_lj(w_k)`` and ``B_l[i, k] = Y_li(R^T w_k)`` gives ``B_l = D_l A_l``, so
    ``M_l = A_l^{-T} B_l^T``.  This is exact up to rounding for any number of bands.
    """
    bands = _check_bands(bands)
    R = _check_rotations(R)
    lead = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    n = bands * bands
    dirs, inverses = _rotation_samples(bands)

    out = np.zeros((Rf.shape[0], n, n))
    out[:, 0, 0] = 1.0
    # Chunks over rotations keep the temporaries small; only the output is large.
    step = _ROTATION_CHUNK
    for start in range(0, Rf.shape[0], step):
        rc = Rf[start : start + step]
        for l in range(1, bands):
            lo, hi = l * l, (l + 1) * (l + 1)
            k = 2 * l + 1
            # R^T w_k as row vectors, one matrix product: rotated[k, r] = w_k^T R[r].
            rotated = np.tensordot(dirs[lo:hi], rc, axes=([1], [1]))
            y = _basis_rows(*_unit_xyz(rotated.reshape(-1, 3)), l + 1)[lo:hi]
            # y[i, k, r] = Y_li(R_r^T w_k); M_l[r, a, i] = sum_k inv(A_l)[k, a] * y[i, k, r].
            y = y.reshape(k, k, rc.shape[0])
            out[start : start + step, lo:hi, lo:hi] = (inverses[l].T @ y).transpose(2, 1, 0)
    return out.reshape(lead + (n, n))


def rotate(coeffs, R) -> np.ndarray:
    """Rotate SH coefficients by one rotation.

    Parameters
    ----------
    coeffs : array_like, shape (bands**2, C) or (bands**2,)
        Coefficients of ``f``.
    R : array_like, shape (3, 3)
        Rotation matrix.

    Returns
    -------
    ndarray, same shape as ``coeffs``, float64
        Coefficients of ``g(w) = f(R^T w)``.

    Raises
    ------
    ValueError
        If ``R`` is not a 3x3 rotation (orthonormal, det +1, within 1e-4).
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"coeffs must have shape (n,) or (n, C), got {coeffs.shape}")
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"rotate() takes one 3x3 rotation, got shape {R.shape}")
    bands = _bands_from_count(coeffs.shape[0])
    return rotation_matrices(R, bands) @ coeffs


# --------------------------------------------------------------------------- Gaunt tensor


@functools.lru_cache(maxsize=None)
def _gaunt_cached(bands: int) -> np.ndarray:
    """Read-only Gaunt tensor for ``bands`` bands (see :func:`gaunt`)."""
    # Product of three band-(bands-1) functions is a polynomial of degree 3*(bands-1) in
    # (x, y, z): Gauss-Legendre with n nodes is exact to degree 2n-1 in cos(theta), and a
    # uniform phi grid of N points is exact for trigonometric degree < N.
    degree = 3 * (bands - 1)
    n_theta = degree // 2 + 2
    n_phi = degree + 2
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    s = np.sqrt(1.0 - z * z)
    dirs = np.stack(
        [s[:, None] * np.cos(phi)[None, :], s[:, None] * np.sin(phi)[None, :],
         np.broadcast_to(z[:, None], (n_theta, n_phi))],
        axis=-1,
    ).reshape(-1, 3)
    weights = np.repeat(wz, n_phi) * (2.0 * np.pi / n_phi)
    y = basis(dirs, bands)
    g = np.einsum("q,qi,qj,qk->ijk", weights, y, y, y, optimize=True)
    # Copy each entry from its sorted index triple so the symmetry is exact, not just to rounding.
    canonical = np.sort(np.indices(g.shape), axis=0)
    g = g[canonical[0], canonical[1], canonical[2]]
    # Analytically zero entries come out as ~1e-17 rounding noise; make them exact zeros.
    g[np.abs(g) < 1e-13] = 0.0
    g.setflags(write=False)
    return g


def gaunt(bands: int = 4) -> np.ndarray:
    """Gaunt tensor of the real SH basis.

    Parameters
    ----------
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands**2, bands**2, bands**2), float64, read-only
        ``G[i, j, k] = integral Y_i Y_j Y_k dw``, computed by exact quadrature (cached).
        Symmetric in all three indices; entries that are analytically zero are exactly 0.
        Use ``gaunt(b).copy()`` for a writeable array.
    """
    return _gaunt_cached(_check_bands(bands))


# --------------------------------------------------------------------------- kernels


def clamped_cosine(bands: int = 4) -> np.ndarray:
    """Zonal SH coefficients of the clamped cosine ``max(0, cos theta)`` about +z.

    Parameters
    ----------
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands,), float64
        ``z_l = integral max(0, cos theta) Y_l0 dw``
        ``= 2*pi*sqrt((2l+1)/(4*pi)) * integral_0^1 z P_l(z) dz``, from an exact recurrence:
        0.886227, 1.023327, 0.495416, 0, -0.110778, ...  Odd l >= 3 are exactly zero.
    """
    bands = _check_bands(bands)
    l = np.arange(bands)
    return 2.0 * np.pi * np.sqrt((2 * l + 1) / (4.0 * np.pi)) * _legendre_moments(1.0, bands)


def zonal_to_band_factors(z) -> np.ndarray:
    """Funk-Hecke band factors of a zonal kernel.

    Parameters
    ----------
    z : array_like, shape (bands,)
        Zonal coefficients ``h_l`` (the ``Y_l0`` coefficients of a kernel symmetric about +z).

    Returns
    -------
    ndarray, shape (bands,), float64
        ``Lambda_l = sqrt(4*pi/(2l+1)) * z_l``: convolving ``f`` with the kernel multiplies
        ``f_lm`` by ``Lambda_l``.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 1:
        raise ValueError(f"zonal coefficients must have shape (bands,), got {z.shape}")
    l = np.arange(z.shape[0])
    return np.sqrt(4.0 * np.pi / (2 * l + 1)) * z


def phong_lobe(exponent: float, bands: int = 4) -> np.ndarray:
    """Band factors of the normalised Phong lobe ``(n+1)/(2*pi) * max(0, cos theta)**n``.

    Parameters
    ----------
    exponent : float
        Real exponent ``n >= 0``.
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands,), float64
        ``Lambda_l = (n+1) * integral_0^1 z**n P_l(z) dz`` (so ``Lambda_0 = 1`` and
        ``Lambda_1 = (n+1)/(n+2)``); exponent 1 gives 1, 2/3, 1/4, 0.  Computed with an exact
        recurrence, accurate to rounding also for large exponents.
    """
    bands = _check_bands(bands)
    n = float(exponent)
    if not math.isfinite(n) or n < 0:
        raise ValueError(f"Phong exponent must be a finite number >= 0, got {exponent!r}")
    return (n + 1.0) * _legendre_moments(n, bands)


def band_factors_to_coeff_scale(lam) -> np.ndarray:
    """Expand per-band factors to per-coefficient factors.

    Parameters
    ----------
    lam : array_like, shape (bands,)
        One factor per band.

    Returns
    -------
    ndarray, shape (bands**2,), float64
        ``lam[l]`` repeated ``2l+1`` times, ready to multiply a coefficient vector.
    """
    lam = np.asarray(lam, dtype=np.float64)
    if lam.ndim != 1:
        raise ValueError(f"band factors must have shape (bands,), got {lam.shape}")
    return np.repeat(lam, 2 * np.arange(lam.shape[0]) + 1)


def window(bands: int, kind: str = "hanning", width: float | None = None) -> np.ndarray:
    """Per-band deringing window (Sloan, "Stupid Spherical Harmonics Tricks").

    Parameters
    ----------
    bands : int
        Number of bands.
    kind : {"hanning", "lanczos"}
        ``hanning``: ``(1 + cos(pi*l/width))/2``; ``lanczos``: ``sinc(l/width)``
        ``= sin(pi*l/width)/(pi*l/width)``.  Both are 0 for ``l >= width``.
    width : float, optional
        Window width in bands; defaults to ``bands`` (so the last band is damped, not zeroed).
        Smaller widths ring less but blur more.

    Returns
    -------
    ndarray, shape (bands,), float64
        Factors, 1 at l = 0 and decreasing with l.  Apply with :func:`apply_window`.
    """
    bands = _check_bands(bands)
    w = float(bands if width is None else width)
    if not w > 0:
        raise ValueError(f"window width must be > 0, got {width!r}")
    t = np.arange(bands) / w
    if kind == "hanning":
        factors = 0.5 * (1.0 + np.cos(np.pi * t))
    elif kind == "lanczos":
        factors = np.sinc(t)
    else:
        raise ValueError(f"unknown window kind {kind!r}; expected 'hanning' or 'lanczos'")
    return np.where(t < 1.0, factors, 0.0)


def apply_window(coeffs, w) -> np.ndarray:
    """Multiply SH coefficients by per-band factors.

    Parameters
    ----------
    coeffs : array_like, shape (bands**2, C) or (bands**2,)
        SH coefficients.
    w : array_like, shape (bands,)
        Per-band factors, e.g. from :func:`window` or :func:`phong_lobe`.

    Returns
    -------
    ndarray, same shape as ``coeffs``, float64
        A new array; ``coeffs`` is not modified.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"coeffs must have shape (n,) or (n, C), got {coeffs.shape}")
    bands = _bands_from_count(coeffs.shape[0])
    scale = band_factors_to_coeff_scale(w)
    if scale.shape[0] != coeffs.shape[0]:
        raise ValueError(f"{bands} bands of coefficients but {np.shape(w)[0]} window factors")
    return coeffs * (scale if coeffs.ndim == 1 else scale[:, None])


def unshadowed_transfer(normals, bands: int = 4, dtype=np.float64) -> np.ndarray:
    """Diffuse transfer of unshadowed points: the clamped cosine / pi turned to each normal.

    The one definition of the "analytic" transfer (segments that need no network, the
    training check that a segment is unshadowed, the GLSL backend's coefficient scale).

    Parameters
    ----------
    normals : array_like, shape (N, 3)
        Unit normals.
    bands : int
        Number of bands.
    dtype : {np.float64, np.float32}
        Precision of the arithmetic (basis and scaling); the ONNX backend's per-frame
        analytic segments use float32.

    Returns
    -------
    ndarray, shape (N, bands**2), float32
    """
    scale = unshadowed_coeff_scale(bands).astype(dtype)
    return (basis(np.asarray(normals, dtype=dtype), bands) * scale).astype(np.float32, copy=False)


def unshadowed_coeff_scale(bands: int = 4) -> np.ndarray:
    """(bands**2,) float64 per-coefficient factors ``s`` with ``unshadowed_transfer(n) = s * Y(n)``."""
    return band_factors_to_coeff_scale(zonal_to_band_factors(clamped_cosine(bands)) / np.pi)


QUADRATIC_TERMS = ("x", "y", "z", "xx", "yy", "zz", "xy", "yz", "zx")
"""The monomials of a unit normal ``n = (x, y, z)`` that :func:`unshadowed_quadratic` weighs, in order."""


def unshadowed_quadratic(bands: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The unshadowed transfer as a quadratic of the unit normal: ``(c0, W)`` with
    ``unshadowed_transfer(n) = c0 + q(n) @ W``, ``q(n)`` the :data:`QUADRATIC_TERMS` of ``n``.

    Exact up to 4 bands: the clamped cosine's band 3 vanishes, and bands 0-2 of the SH basis are
    polynomials of degree <= 2; from band 4 on the transfer is not a quadratic (ValueError).
    Used where the transfer is split into this known part and a learnt or interpolated residual
    (:mod:`prt.train.networks.network`, :mod:`prt.runtime.interpolation`).

    Returns
    -------
    c0 : (bands**2,) float64
    W : (9, bands**2) float64
    """
    bands = _check_bands(bands)
    if bands > 4:
        raise ValueError(f"the unshadowed transfer is a quadratic of the normal only up to 4 bands, not {bands}")
    return tuple(a.copy() for a in _unshadowed_quadratic(bands))


@functools.lru_cache(maxsize=None)
def _unshadowed_quadratic(bands: int) -> tuple[np.ndarray, np.ndarray]:
    normals = np.random.default_rng(0).normal(size=(256, 3))
    x, y, z = (normals := normals / np.linalg.norm(normals, axis=1, keepdims=True)).T
    terms = np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, y * z, z * x], axis=1)
    target = basis(normals, bands) * unshadowed_coeff_scale(bands)
    fit = np.linalg.lstsq(terms, target, rcond=None)[0]
    if np.abs(terms @ fit - target).max() > 1e-9:  # the basis changed its convention
        raise RuntimeError("the unshadowed transfer is not a quadratic of the normal")
    fit[np.abs(fit) < 1e-12] = 0.0  # exact zeros where a coefficient has no such term
    return fit[0], fit[1:]


def white_furnace_transfer(bands: int = 4) -> np.ndarray:
    """Diffuse transfer vector of an unoccluded point with normal +z.

    Parameters
    ----------
    bands : int
        Number of bands.

    Returns
    -------
    ndarray, shape (bands**2,), float64
        ``T_i = (1/pi) * integral max(0, n.w) Y_i(w) dw``: ``clamped_cosine(bands)/pi`` at the
        ``m = 0`` slots and 0 elsewhere.  With the project normalisation (transfer includes
        ``1/pi``) a constant environment of radiance 1 (``L_00 = sqrt(4*pi)``) gives
        ``dot(T, L) = 1``.
    """
    bands = _check_bands(bands)
    t = np.zeros(bands * bands)
    l = np.arange(bands)
    t[l * (l + 1)] = clamped_cosine(bands) / np.pi
    return t
