"""Tests of prt.runtime.sh: conventions, quadrature-exact identities, rotation, kernels."""

import math

import numpy as np
import pytest

from prt.runtime import sh

SQRT_4PI = math.sqrt(4.0 * math.pi)


def sphere_quadrature(n_theta, n_phi):
    """Gauss-Legendre in cos(theta) x uniform phi: directions (N, 3) and weights (N,)."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    s = np.sqrt(1.0 - z * z)
    dirs = np.stack(
        [np.outer(s, np.cos(phi)), np.outer(s, np.sin(phi)), np.outer(z, np.ones(n_phi))], -1
    )
    return dirs.reshape(-1, 3), np.repeat(wz, n_phi) * 2.0 * np.pi / n_phi


def random_rotations(n, seed=0):
    """n uniformly random rotation matrices (n, 3, 3) from unit quaternions."""
    q = np.random.default_rng(seed).normal(size=(n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(n, 3, 3)


def random_dirs(n, seed=1):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def band_energy(c):
    bands = math.isqrt(c.shape[0])
    return np.array([np.sum(c[l * l : (l + 1) ** 2] ** 2, axis=0) for l in range(bands)])


# --------------------------------------------------------------------------- basis


@pytest.mark.parametrize("bands", [6, 12])
def test_basis_orthonormal_by_quadrature(bands):
    dirs, w = sphere_quadrature(bands + 1, 2 * bands + 1)
    y = sh.basis(dirs, bands)
    gram = y.T @ (w[:, None] * y)
    np.testing.assert_allclose(gram, np.eye(bands * bands), atol=1e-12)


def test_basis_low_order_values_and_sign_convention():
    c0 = 0.5 / math.sqrt(math.pi)
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    y = sh.basis(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-2.0, 0, 0]]), 2)
    assert c0 == pytest.approx(0.282095, abs=1e-6)
    np.testing.assert_allclose(y[:, 0], c0, atol=1e-15)
    np.testing.assert_allclose(y[0, 1:], [c1, 0, 0], atol=1e-15)  # +y -> Y_{1,-1}
    np.testing.assert_allclose(y[1, 1:], [0, c1, 0], atol=1e-15)  # +z -> Y_{1,0}
    np.testing.assert_allclose(y[2, 1:], [0, 0, c1], atol=1e-15)  # +x -> Y_{1,1} (no CS phase)
    np.testing.assert_allclose(y[3, 1:], [0, 0, -c1], atol=1e-15)  # normalised inside
    # Band 2 at a generic direction, from the closed forms of these conventions.
    x_, y_, z_ = random_dirs(1)[0]
    expected = [
        1.092548430592079 * x_ * y_,
        1.092548430592079 * y_ * z_,
        0.315391565252520 * (3 * z_ * z_ - 1),
        1.092548430592079 * x_ * z_,
        0.546274215296040 * (x_ * x_ - y_ * y_),
    ]
    np.testing.assert_allclose(sh.basis([x_, y_, z_], 3)[4:], expected, atol=1e-14)


def test_basis_matches_scipy_for_many_bands():
    special = pytest.importorskip("scipy.special")
    if not hasattr(special, "sph_harm_y"):
        pytest.skip("scipy too old for sph_harm_y")
    bands = 10
    d = random_dirs(500)
    theta, phi = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    ref = np.empty((500, bands * bands))
    for l in range(bands):
        for m in range(-l, l + 1):
            # scipy includes the Condon-Shortley phase (-1)^m, which our convention drops.
            c = special.sph_harm_y(l, abs(m), theta, phi) * (-1) ** abs(m)
            v = c.real if m == 0 else math.sqrt(2) * (c.real if m > 0 else c.imag)
            ref[:, l * (l + 1) + m] = v
    np.testing.assert_allclose(sh.basis(d, bands), ref, atol=1e-12)


def test_basis_dtypes_shapes_and_zero_vectors():
    d = random_dirs(10).reshape(2, 5, 3)
    y64 = sh.basis(d, 3)
    y32 = sh.basis(d.astype(np.float32), 3)
    assert y64.shape == (2, 5, 9) and y64.dtype == np.float64
    assert y32.shape == (2, 5, 9) and y32.dtype == np.float32
    np.testing.assert_allclose(y32, y64, atol=1e-6)
    assert sh.basis(np.array([1, 0, 0]), 4).dtype == np.float64
    assert sh.basis([1.0, 2.0, 3.0]).shape == (16,)
    y0 = sh.basis(np.zeros((3, 3)), 4)
    assert np.isfinite(y0).all()
    np.testing.assert_allclose(y0, sh.basis(np.tile([0.0, 0, 1], (3, 1)), 4))
    with pytest.raises(ValueError):
        sh.basis(np.zeros((4, 2)))
    with pytest.raises(ValueError):
        sh.basis(np.zeros((4, 3)), 0)


def test_basis_chunking_is_seamless():
    d = random_dirs(40000, seed=5)  # more than one internal chunk
    y = sh.basis(d, 5)
    np.testing.assert_array_equal(y[-7:], sh.basis(d[-7:], 5))


def test_evaluate_shapes_and_validation():
    coeffs = np.random.default_rng(2).normal(size=(9, 3))
    d = random_dirs(7).reshape(7, 1, 3)
    out = sh.evaluate(coeffs, d)
    assert out.shape == (7, 1, 3)
    np.testing.assert_allclose(out[:, 0], sh.basis(d[:, 0], 3) @ coeffs)
    assert sh.evaluate(coeffs[:, 0], d).shape == (7, 1)
    with pytest.raises(ValueError, match="square"):
        sh.evaluate(np.zeros((10, 3)), d)


# --------------------------------------------------------------------------- env maps


def test_envmap_axis_conventions_and_round_trip():
    h, w = 16, 32
    dirs = sh.envmap_directions(h, w)
    assert dirs.shape == (h, w, 3) and dirs.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-15)
    # Top row points (nearly) up, bottom row (nearly) down.
    assert dirs[0, :, 1].min() == pytest.approx(math.cos(math.pi / (2 * h)))
    assert dirs[-1, :, 1].max() == pytest.approx(-math.cos(math.pi / (2 * h)))
    uv = sh.direction_to_equirect_uv(
        np.array([[0, 0, -1.0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, 1, 0], [0, -3, 0]])
    )
    np.testing.assert_allclose(uv[0], [0.5, 0.5])  # image centre is -Z
    np.testing.assert_allclose(uv[1], [0.75, 0.5])  # u = 0.75 is +X
    np.testing.assert_allclose(uv[2], [0.25, 0.5])
    assert uv[3, 0] in (0.0, 1.0) or uv[3, 0] == pytest.approx(0.0)  # edges are +Z
    assert uv[3, 1] == pytest.approx(0.5)
    assert uv[4, 1] == 0.0 and uv[5, 1] == 1.0
    # Texel centres map back to their own (u, v).
    uv = sh.direction_to_equirect_uv(dirs)
    np.testing.assert_allclose(uv[..., 0], ((np.arange(w) + 0.5) / w)[None, :].repeat(h, 0))
    np.testing.assert_allclose(uv[..., 1], ((np.arange(h) + 0.5) / h)[:, None].repeat(w, 1))


@pytest.mark.parametrize("shape", [(64, 128), (37, 74), (1, 3)])
def test_solid_angles_sum_to_4pi(shape):
    omega = sh.texel_solid_angles(*shape)
    assert omega.shape == shape
    assert omega.sum() == pytest.approx(4 * math.pi, abs=1e-12)
    assert (omega > 0).all()


@pytest.mark.parametrize("shape", [(64, 128), (37, 74)])
def test_constant_envmap_projects_to_l00(shape):
    coeffs = sh.project_envmap(np.ones(shape + (3,), np.float32), bands=4)
    assert coeffs.shape == (16, 3) and coeffs.dtype == np.float64
    np.testing.assert_allclose(coeffs[0], SQRT_4PI, atol=1e-9)
    # Terms odd about the equator or varying around +Y cancel exactly; the rest carry the
    # O(1/H^2) error of the midpoint rule in theta.
    assert np.abs(coeffs[1:]).max() < 3.0 / shape[0] ** 2


def test_white_furnace():
    t = sh.white_furnace_transfer(4)
    assert t.shape == (16,)
    assert t @ np.r_[SQRT_4PI, np.zeros(15)] == pytest.approx(1.0, abs=1e-14)
    radiance = sh.project_envmap(np.ones((64, 128, 3)))
    np.testing.assert_allclose(t @ radiance, 1.0, atol=1e-4)
    np.testing.assert_allclose(t[[0, 2, 6, 12]], sh.clamped_cosine(4) / math.pi)
    assert np.count_nonzero(t) == 3  # l = 3 is zero
    # It is the projection of max(0, z)/pi, the cosine lobe about +z.
    dirs = sh.envmap_directions(256, 512)
    image = np.repeat(np.maximum(dirs[..., 2:], 0.0) / math.pi, 3, axis=-1)
    np.testing.assert_allclose(sh.project_envmap(image)[:, 0], t, atol=1e-3)


def test_projection_recovers_known_coefficients():
    known = np.random.default_rng(3).normal(size=(16, 3))
    image = sh.evaluate(known, sh.envmap_directions(256, 512))
    np.testing.assert_allclose(sh.project_envmap(image, 4), known, atol=1e-3)


def test_project_envmap_rejects_bad_input():
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        sh.project_envmap(np.ones((8, 16)))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        sh.project_envmap(np.ones((8, 16, 4)))
    bad = np.ones((8, 16, 3))
    bad[2, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        sh.project_envmap(bad)
    bad[2, 3, 1] = np.inf
    with pytest.raises(ValueError, match="Inf"):
        sh.project_envmap(bad)


# --------------------------------------------------------------------------- rotation


def test_rotation_known_case_z_to_x():
    # Rotation by +90 degrees about +y carries +z to +x, so the "z" lobe becomes the "x" lobe.
    r = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0])
    c = np.zeros(4)
    c[2] = 1.0
    np.testing.assert_allclose(sh.rotate(c, r), [0, 0, 0, 1], atol=1e-12)


@pytest.mark.parametrize("bands", [1, 2, 3, 4, 5, 6])
def test_rotation_properties(bands):
    n = bands * bands
    rng = np.random.default_rng(bands)
    c = rng.normal(size=(n, 3))
    r1, r2 = random_rotations(2, seed=bands)
    rotated = sh.rotate(c, r1)
    assert rotated.shape == (n, 3)
    np.testing.assert_allclose(band_energy(rotated), band_energy(c), rtol=1e-10)
    np.testing.assert_allclose(sh.rotate(rotated, r2), sh.rotate(c, r2 @ r1), atol=1e-10)
    np.testing.assert_allclose(sh.rotate(c, np.eye(3)), c, atol=1e-12)
    w = random_dirs(50, seed=bands + 10)
    np.testing.assert_allclose(sh.evaluate(rotated, w), sh.evaluate(c, w @ r1), atol=1e-10)
    m = sh.rotation_matrices(r1, bands)
    np.testing.assert_allclose(m @ m.T, np.eye(n), atol=1e-10)  # orthogonal
    np.testing.assert_allclose(sh.rotate(c[:, 0], r1), rotated[:, 0])


def test_rotation_high_band_accuracy():
    c = np.random.default_rng(7).normal(size=100)
    r = random_rotations(1, seed=7)[0]
    w = random_dirs(200, seed=8)
    np.testing.assert_allclose(sh.evaluate(sh.rotate(c, r), w), sh.evaluate(c, w @ r), atol=1e-8)


def test_rotation_matrices_batched_and_block_diagonal():
    rots = random_rotations(6, seed=4).reshape(2, 3, 3, 3)
    m = sh.rotation_matrices(rots, 4)
    assert m.shape == (2, 3, 16, 16)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(m[i, j], sh.rotation_matrices(rots[i, j], 4), atol=1e-13)
    mask = np.zeros((16, 16), bool)
    for l in range(4):
        mask[l * l : (l + 1) ** 2, l * l : (l + 1) ** 2] = True
    assert np.all(m[..., ~mask] == 0.0)
    many = random_rotations(5000, seed=9)  # several internal chunks
    np.testing.assert_allclose(
        sh.rotation_matrices(many, 3)[4321], sh.rotation_matrices(many[4321], 3), atol=1e-13
    )


def test_rotate_rejects_non_rotations():
    c = np.zeros(16)
    with pytest.raises(ValueError, match="not a rotation"):
        sh.rotate(c, 2.0 * np.eye(3))
    with pytest.raises(ValueError, match="not a rotation"):
        sh.rotate(c, np.diag([1.0, 1.0, -1.0]))  # a reflection
    with pytest.raises(ValueError, match="not a rotation"):
        sh.rotation_matrices(np.stack([np.eye(3), np.ones((3, 3))]))
    with pytest.raises(ValueError):
        sh.rotate(c, np.eye(4))
    # Within tolerance is accepted.
    sh.rotate(c, np.eye(3) + 1e-6)


# --------------------------------------------------------------------------- Gaunt


def test_gaunt_values_count_and_symmetry():
    g = sh.gaunt(4)
    assert g.shape == (16, 16, 16) and g.dtype == np.float64
    assert not g.flags.writeable
    np.testing.assert_allclose(np.diagonal(g[0]), 0.282094792, atol=1e-9)
    assert g[2, 2, 6] == pytest.approx(0.252313252, abs=1e-9)
    assert g[6, 6, 6] == pytest.approx(0.180223752, abs=1e-9)
    assert np.count_nonzero(np.abs(g) > 1e-10) == 353
    for axes in [(1, 0, 2), (0, 2, 1), (2, 1, 0), (1, 2, 0), (2, 0, 1)]:
        np.testing.assert_array_equal(g, g.transpose(axes))
    assert sh.gaunt(4) is g  # cached
    np.testing.assert_allclose(sh.gaunt(5)[:16, :16, :16], g, atol=1e-14)


def test_gaunt_matches_product_projection():
    # Projecting Y_i * Y_j with a fine independent quadrature reproduces G[i, j, :].
    g = sh.gaunt(3)
    dirs, w = sphere_quadrature(12, 25)
    y = sh.basis(dirs, 3)
    np.testing.assert_allclose(np.einsum("q,qi,qj,qk->ijk", w, y, y, y), g, atol=1e-13)


# --------------------------------------------------------------------------- kernels


def test_clamped_cosine():
    z = sh.clamped_cosine(4)
    np.testing.assert_allclose(z, [0.886227, 1.023327, 0.495416, 0.0], atol=1e-6)
    assert z[3] == 0.0
    # Higher bands against Gauss-Legendre quadrature of 2*pi*sqrt((2l+1)/4pi) * int_0^1 z P_l.
    t, wt = np.polynomial.legendre.leggauss(40)
    zz, ww = 0.5 * (t + 1), 0.5 * wt
    ref = [
        2 * math.pi * math.sqrt((2 * l + 1) / (4 * math.pi))
        * np.sum(ww * zz * np.polynomial.legendre.legval(zz, np.eye(l + 1)[l]))
        for l in range(12)
    ]
    np.testing.assert_allclose(sh.clamped_cosine(12), ref, atol=1e-13)


def test_zonal_band_factors_and_coeff_scale():
    lam = sh.zonal_to_band_factors(sh.clamped_cosine(4))
    np.testing.assert_allclose(lam, [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0], atol=1e-12)
    np.testing.assert_allclose(lam / math.pi, sh.phong_lobe(1.0, 4), atol=1e-14)
    scale = sh.band_factors_to_coeff_scale([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(scale, [1, 2, 2, 2, 3, 3, 3, 3, 3])


@pytest.mark.parametrize("n", [1, 8, 32, 500])
def test_phong_lobe_first_band(n):
    lam = sh.phong_lobe(n, 6)
    assert lam[0] == pytest.approx(1.0, abs=1e-15)
    assert lam[1] == pytest.approx((n + 1) / (n + 2), abs=1e-14)


def test_phong_lobe_exponent_one_and_exact_reference():
    np.testing.assert_allclose(sh.phong_lobe(1, 4), [1, 2 / 3, 1 / 4, 0], atol=1e-15)
    # Independent reference: expand P_l in monomials, int_0^1 z^(n+k) dz = 1/(n+k+1).
    for n in [0, 3, 17.3, 1000, 1000.5]:
        ref = [
            (n + 1) * sum(
                c / (n + k + 1)
                for k, c in enumerate(np.polynomial.legendre.leg2poly(np.eye(l + 1)[l]))
            )
            for l in range(8)
        ]
        np.testing.assert_allclose(sh.phong_lobe(n, 8), ref, atol=1e-10)
    with pytest.raises(ValueError):
        sh.phong_lobe(-1.0)


def test_windows():
    for kind in ["hanning", "lanczos"]:
        w = sh.window(6, kind)
        assert w.shape == (6,) and w[0] == 1.0
        assert np.all(np.diff(w) < 0) and w[-1] > 0
        narrow = sh.window(6, kind, width=3)
        assert np.all(narrow[3:] == 0.0) and np.all(np.diff(narrow[:4]) < 0)
    hanning = 0.5 * (1 + np.cos(np.pi * np.arange(4) / 4))
    np.testing.assert_allclose(sh.window(4, "hanning"), hanning)
    with pytest.raises(ValueError, match="kind"):
        sh.window(4, "gauss")
    c = np.ones((16, 3))
    windowed = sh.apply_window(c, sh.window(4))
    np.testing.assert_allclose(windowed[:, 0], sh.band_factors_to_coeff_scale(sh.window(4)))
    assert np.all(c == 1.0)  # input untouched
    assert sh.apply_window(np.ones(9), [1, 0.5, 0.25]).tolist() == [1] + [0.5] * 3 + [0.25] * 5
    with pytest.raises(ValueError):
        sh.apply_window(c, sh.window(3))


@pytest.mark.parametrize("bands", [1, 2, 3, 4])
def test_unshadowed_transfer_is_the_quadratic_of_the_normal(bands):
    """c0 + q(n) @ W equals the definition at normals it was not fitted on; band 4 on is refused."""
    n = np.random.default_rng(7).normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c0, w = sh.unshadowed_quadratic(bands)
    x, y, z = n.T
    q = np.stack([x, y, z, x * x, y * y, z * z, x * y, y * z, z * x], axis=1)
    assert len(sh.QUADRATIC_TERMS) == 9 and w.shape == (9, bands * bands)
    np.testing.assert_allclose(c0 + q @ w, sh.basis(n, bands) * sh.unshadowed_coeff_scale(bands), atol=1e-12)
    with pytest.raises(ValueError, match="4 bands"):
        sh.unshadowed_quadratic(5)
