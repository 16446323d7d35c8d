"""Shading: light matrix, white furnace, glossy against quadrature, numpy vs GLSL, tone mapping."""

from __future__ import annotations

import re

import moderngl
import numpy as np
import pytest

from prt.runtime import sh
from prt.runtime.envmap import load_envmap_sh
from prt.runtime.envmaps import bundled_envmap_path
from prt.runtime.gl import run_fragment_program
from prt.runtime.shading import (
    GLSL_DEFINES,
    GLSL_FILES,
    MATERIAL_KINDS,
    TONEMAP_MAX,
    Lighting,
    Material,
    compute_light_matrix,
    glsl_source,
    linear_to_srgb,
    reflect,
    shade,
    shader_uniforms,
    to_srgb8,
    tonemap,
)
from prt.shaders import assemble
from prt.shaders import source as shader_source

BANDS = 4
N_COEFFS = BANDS * BANDS
# Constant environment of radiance 1 in every channel.
WHITE = np.zeros((N_COEFFS, 3))
WHITE[0] = np.sqrt(4.0 * np.pi)
# Per-coefficient factors turning sh.basis(n) into the transfer of an unoccluded point.
COSINE_SCALE = sh.band_factors_to_coeff_scale(sh.zonal_to_band_factors(sh.clamped_cosine(BANDS)) / np.pi)


# --------------------------------------------------------------------------- helpers


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def unoccluded_transfer(normals: np.ndarray) -> np.ndarray:
    """Transfer of unoccluded points: (1/pi) max(0, n.w) projected on 4 bands, shape (N, 16)."""
    return sh.basis(normals, BANDS) * COSINE_SCALE


def quadrature(n_theta: int, n_phi: int, axis=None, hemisphere: bool = False):
    """Gauss-Legendre in cos(theta) x uniform phi about ``axis`` (default +z).

    Exact for polynomials in the direction of degree < min(2 * n_theta, n_phi), over the sphere
    or (``hemisphere``) over the half with ``axis . w >= 0``.
    """
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    if hemisphere:
        z, wz = (z + 1.0) / 2.0, wz / 2.0
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    s = np.sqrt(1.0 - z * z)
    dirs = np.stack(
        [s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), np.broadcast_to(z[:, None], (n_theta, n_phi))],
        axis=-1,
    ).reshape(-1, 3)
    weights = np.repeat(wz, n_phi) * (2.0 * np.pi / n_phi)
    if axis is not None:
        a = unit(np.asarray(axis, dtype=np.float64))
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = unit(np.cross(helper, a))
        dirs = dirs @ np.stack([e1, np.cross(a, e1), a])
    return dirs, weights


def lobe_at(dirs: np.ndarray, exponent: float) -> np.ndarray:
    """Phong band factors times the basis at ``dirs``, shape (N, 16)."""
    return sh.basis(dirs, BANDS) * sh.band_factors_to_coeff_scale(sh.phong_lobe(exponent, BANDS))


def random_views(rng, normals: np.ndarray) -> np.ndarray:
    """Random unit view directions on the side of each normal."""
    v = unit(rng.normal(size=normals.shape))
    return v - 2.0 * np.minimum(0.0, np.sum(v * normals, axis=-1, keepdims=True)) * normals


# --------------------------------------------------------------------------- light matrix


def test_light_matrix_matches_triple_product_quadrature():
    rng = np.random.default_rng(0)
    L = rng.normal(size=(N_COEFFS, 3))
    T = rng.normal(size=N_COEFFS)
    # Y_i Y_j Y_k has degree 9: 12 x 24 nodes are exact; 24 x 48 leaves margin.
    dirs, w = quadrature(24, 48)
    y = sh.basis(dirs, BANDS)
    expected = np.einsum("q,qc,qj,qk->ckj", w, y @ L, y, y)
    M = compute_light_matrix(L)
    assert M.shape == (3, N_COEFFS, N_COEFFS)
    np.testing.assert_allclose(M, expected, atol=1e-12)
    # M_c @ T are the coefficients of the product function L_c(w) * T~(w).
    product = np.einsum("q,qc,q,qk->ck", w, y @ L, y @ T, y)
    np.testing.assert_allclose(M @ T, product, atol=1e-12)


def test_light_matrix_symmetries():
    rng = np.random.default_rng(1)
    L, L2 = rng.normal(size=(2, N_COEFFS, 3))
    T, T2 = rng.normal(size=(2, N_COEFFS))
    M = compute_light_matrix(L)
    np.testing.assert_allclose(M, M.transpose(0, 2, 1), atol=1e-14)  # G is fully symmetric
    # Constant radiance 1 multiplies by 1: the identity.
    identity = np.broadcast_to(np.eye(N_COEFFS), (3, N_COEFFS, N_COEFFS))
    np.testing.assert_allclose(compute_light_matrix(WHITE), identity, atol=1e-14)
    # The product is commutative: light times transfer == transfer (as a light) times light.
    T_as_light = np.repeat(T[:, None], 3, axis=1)
    swapped = np.einsum("ckj,jc->ck", compute_light_matrix(T_as_light), L)
    np.testing.assert_allclose(M @ T, swapped, atol=1e-12)
    # Linear in L, and the bilinear form T^T M T2 is symmetric.
    np.testing.assert_allclose(compute_light_matrix(2 * L - L2), 2 * M - compute_light_matrix(L2), atol=1e-12)
    np.testing.assert_allclose(T @ M @ T2, T2 @ M @ T, atol=1e-12)


def test_lighting_caches_read_only_light_matrix_and_rotates_first():
    rng = np.random.default_rng(2)
    L = rng.normal(size=(N_COEFFS, 3))
    R = random_rotation(rng)
    lighting = Lighting.from_sh(L, rotation=R)
    assert lighting.bands == 4
    np.testing.assert_allclose(lighting.sh, sh.rotate(L, R), atol=1e-12)
    np.testing.assert_allclose(lighting.light_matrix, compute_light_matrix(sh.rotate(L, R)), atol=1e-12)
    assert not lighting.sh.flags.writeable and not lighting.light_matrix.flags.writeable
    assert lighting.light_matrix is lighting.light_matrix


def test_rotated_environment_equals_counter_rotated_scene():
    """Turning the environment by R shades a point like turning the point by R^T."""
    rng = np.random.default_rng(3)
    L = rng.normal(size=(N_COEFFS, 3))
    L[0] += 6.0
    R = random_rotation(rng)
    normals = unit(rng.normal(size=(64, 3)))
    views = random_views(rng, normals)
    material = Material("glossy", albedo=(0.3, 0.5, 0.7), specular=0.4, exponent=5.0)
    turned = shade(unoccluded_transfer(normals @ R), normals @ R, views @ R, Lighting.from_sh(L), material)
    direct = shade(unoccluded_transfer(normals), normals, views, Lighting.from_sh(L, rotation=R), material)
    np.testing.assert_allclose(direct, turned, rtol=1e-5, atol=1e-5)


def test_from_envmap_projects_the_file():
    path = bundled_envmap_path("studio")
    R = random_rotation(np.random.default_rng(4))
    lighting = Lighting.from_envmap(path, rotation=R, bands=3)
    np.testing.assert_allclose(lighting.sh, sh.rotate(load_envmap_sh(path, 3), R), atol=1e-10)
    assert lighting.light_matrix.shape == (3, 9, 9)


# --------------------------------------------------------------------------- white furnace


def test_white_furnace_diffuse_gives_albedo():
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(500, 3)) * rng.uniform(0.1, 3.0, size=(500, 1))  # not unit length
    albedo = (0.2, 0.5, 0.9)
    for rotation in (None, random_rotation(rng)):  # a constant environment ignores rotation
        lighting = Lighting.from_sh(WHITE, rotation=rotation)
        out = shade(unoccluded_transfer(normals), normals, -normals, lighting, Material(albedo=albedo))
        assert out.dtype == np.float32 and out.shape == (500, 3)
        np.testing.assert_allclose(out, np.broadcast_to(albedo, out.shape), atol=1e-6)
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(unoccluded_transfer(up), sh.white_furnace_transfer(BANDS), atol=1e-15)


def furnace_specular_at_normal_incidence(exponent: float) -> float:
    """sum_l Lambda_l * cosine band factor_l * (2l+1) / (4 pi): sum_m Y_lm(n)^2 = (2l+1)/(4 pi)."""
    l = np.arange(BANDS)
    cosine = sh.zonal_to_band_factors(sh.clamped_cosine(BANDS))
    return float(np.sum(sh.phong_lobe(exponent, BANDS) * cosine * (2 * l + 1) / (4 * np.pi)))


def test_white_furnace_glossy_and_exponent_to_zero():
    rng = np.random.default_rng(6)
    normals = unit(rng.normal(size=(100, 3)))
    lighting = Lighting.from_sh(WHITE)
    for exponent in (1e-9, 1.0, 8.0, 40.0):
        material = Material("glossy", albedo=(0.1, 0.2, 0.3), specular=(0.5, 0.25, 1.0), exponent=exponent)
        out = shade(unoccluded_transfer(normals), normals, normals, lighting, material)
        spec = furnace_specular_at_normal_incidence(exponent)
        expected = np.add(material.albedo, np.multiply(material.specular, spec))
        np.testing.assert_allclose(out, np.broadcast_to(expected, out.shape), atol=2e-6)
        # Up to 4-band truncation the furnace gives the lobe's albedo (e+1)/(e+2).
        assert abs(spec - (exponent + 1) / (exponent + 2)) < 0.1
    # e -> 0: uniform hemisphere lobe, exactly 1/2 at normal incidence, and shading is continuous.
    assert furnace_specular_at_normal_incidence(0.0) == pytest.approx(0.5, abs=1e-15)
    L = rng.normal(size=(N_COEFFS, 3))
    T = rng.normal(size=(100, N_COEFFS))
    views = random_views(rng, normals)
    near_zero = shade(T, normals, views, Lighting.from_sh(L), Material("glossy", exponent=1e-12))
    small = shade(T, normals, views, Lighting.from_sh(L), Material("glossy", exponent=1e-6))
    assert np.isfinite(near_zero).all()
    np.testing.assert_allclose(near_zero, small, atol=1e-5)


# --------------------------------------------------------------------------- glossy vs brute force


def reference_specular(L, T_function_at, normal, view, exponent, dirs, weights):
    """pi * sum_k Lambda_k Y_k(r) * integral L(w) T(w) Y_k(w) dw, by the given quadrature."""
    y = sh.basis(dirs, BANDS)
    product = np.einsum("q,qc,q,qk->ck", weights, y @ L, T_function_at(dirs), y)  # (3, 16)
    r = 2.0 * np.dot(normal, view) * normal - view  # mirror of the view direction about n
    return np.pi * product @ lobe_at(r, exponent)


@pytest.mark.parametrize("exponent", [0.5, 3.0, 12.0])
def test_glossy_constant_light_matches_true_clamped_cosine_product(exponent):
    """Constant L: projecting L(w) max(0, n.w)/pi onto 4 bands is exactly L times T."""
    rng = np.random.default_rng(7)
    L = np.zeros((N_COEFFS, 3))
    L[0] = np.sqrt(4 * np.pi) * np.array([0.7, 1.0, 1.8])
    material = Material("glossy", albedo=(0.4, 0.3, 0.2), specular=(0.6, 0.9, 0.3), exponent=exponent)
    for _ in range(8):
        n = unit(rng.normal(size=3))
        v = random_views(rng, n[None])[0]
        dirs, w = quadrature(8, 16, axis=n, hemisphere=True)  # exact: the integrand has degree 4
        spec = reference_specular(L, lambda d: np.maximum(d @ n, 0.0) / np.pi, n, v, exponent, dirs, w)
        radiance = L[0] / np.sqrt(4 * np.pi)
        expected = np.multiply(material.albedo, radiance) + np.multiply(material.specular, spec)
        out = shade(unoccluded_transfer(n)[None], n[None], v[None], Lighting.from_sh(L), material)[0]
        np.testing.assert_allclose(out, expected, rtol=1e-6)


@pytest.mark.parametrize("exponent", [1.0, 6.0])
def test_glossy_random_light_matches_band_limited_product(exponent):
    """Random 4-band L and T: the Gaunt path equals quadrature of L(w) * T~(w) (T~ from T)."""
    rng = np.random.default_rng(8)
    L = rng.normal(size=(N_COEFFS, 3))
    L[0] += 8.0
    lighting = Lighting.from_sh(L)
    material = Material("glossy", albedo=0.0, specular=1.0, exponent=exponent)
    dirs, w = quadrature(16, 32)  # exact for the degree-9 product
    for _ in range(8):
        n = unit(rng.normal(size=3))
        v = random_views(rng, n[None])[0]
        T = unoccluded_transfer(n) + 0.05 * rng.normal(size=N_COEFFS)
        spec = reference_specular(L, lambda d: sh.basis(d, BANDS) @ T, n, v, exponent, dirs, w)
        out = shade(T[None], n[None], v[None], lighting, material)[0]
        np.testing.assert_allclose(out, np.maximum(spec, 0.0), rtol=1e-6, atol=1e-6 * np.abs(spec).max())


def test_glossy_smooth_light_is_close_to_true_product():
    """Band-1 L: 4-band T drops the l >= 4 cosine terms, a few percent of the specular result."""
    rng = np.random.default_rng(9)
    worst = 0.0
    for _ in range(10):
        L = np.zeros((N_COEFFS, 3))
        L[0] = np.sqrt(4 * np.pi)
        L[1:4] = 0.8 * rng.normal(size=(3, 3))
        n = unit(rng.normal(size=3))
        v = random_views(rng, n[None])[0]
        dirs, w = quadrature(8, 16, axis=n, hemisphere=True)
        spec = reference_specular(L, lambda d: np.maximum(d @ n, 0.0) / np.pi, n, v, 4.0, dirs, w)
        material = Material("glossy", albedo=0.0, specular=1.0, exponent=4.0)
        out = shade(unoccluded_transfer(n)[None], n[None], v[None], Lighting.from_sh(L), material)[0]
        worst = max(worst, np.abs(out - np.maximum(spec, 0)).max() / np.abs(spec).max())
    assert worst < 0.05


def test_reflection_direction_convention():
    n = np.array([[0.0, 0.0, 2.0]])
    np.testing.assert_allclose(reflect(n, n), [[0.0, 0.0, 1.0]], atol=1e-15)  # normal incidence: r = n
    a = 0.3
    v = np.array([[np.sin(a), 0.0, np.cos(a)]])
    np.testing.assert_allclose(reflect(v, n), [[-np.sin(a), 0.0, np.cos(a)]], atol=1e-15)
    rng = np.random.default_rng(10)
    normals, views = unit(rng.normal(size=(2, 50, 3)))
    r = reflect(3.0 * views, normals)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(r * normals, 1), np.sum(views * normals, 1), atol=1e-12)
    # Same normal component, opposite tangential component.
    tangential_v = views - np.sum(views * normals, 1, keepdims=True) * normals
    tangential_r = r - np.sum(r * normals, 1, keepdims=True) * normals
    np.testing.assert_allclose(tangential_r, -tangential_v, atol=1e-12)

    # Shading reads the lobe at r, not at v: a lighting that tells the two apart.
    L = rng.normal(size=(N_COEFFS, 3))
    lighting = Lighting.from_sh(L)
    material = Material("glossy", albedo=0.0, specular=1.0, exponent=8.0)
    normal = np.array([0.0, 0.0, 1.0])
    T = unoccluded_transfer(normal)
    transferred = lighting.light_matrix @ T  # (3, 16)
    at_r = np.pi * transferred @ lobe_at(np.array([-np.sin(a), 0.0, np.cos(a)]), 8.0)
    at_v = np.pi * transferred @ lobe_at(v[0], 8.0)
    out = shade(T[None], normal[None], v, lighting, material)[0]
    np.testing.assert_allclose(out, np.maximum(at_r, 0.0), rtol=1e-6, atol=1e-6)
    assert np.abs(at_r - at_v).max() > 0.05
    out_normal = shade(T[None], normal[None], normal[None], lighting, material)[0]
    at_n = np.pi * transferred @ lobe_at(normal, 8.0)
    np.testing.assert_allclose(out_normal, np.maximum(at_n, 0.0), rtol=1e-6, atol=1e-6)


def test_shade_accepts_image_shapes_and_clamps_negative():
    rng = np.random.default_rng(11)
    T = rng.normal(size=(4, 5, N_COEFFS))
    normals = rng.normal(size=(4, 5, 3))
    out = shade(T, normals, normals, Lighting.from_sh(rng.normal(size=(16, 3))), Material("glossy"))
    assert out.shape == (4, 5, 3) and out.dtype == np.float32
    assert (out >= 0).all() and (out == 0).any()  # random lighting rings negative somewhere
    rows = normals.reshape(-1, 3)
    flat = shade(T.reshape(-1, N_COEFFS), rows, rows, Lighting.from_sh(rng.normal(size=(16, 3))), Material())
    assert flat.shape == (20, 3)


# --------------------------------------------------------------------------- GLSL


def test_glsl_sources_are_includable():
    for name in GLSL_FILES:
        text = shader_source(name)
        assert not re.search(r"^\s*#\s*version", text, flags=re.M)
        for kind, ident in re.findall(r"^\s*(uniform|const)\s+\w+\s+(\w+)", text, flags=re.M):
            assert ident.startswith("u_" if kind == "uniform" else "PRT_"), ident
        for ident in re.findall(r"^(?:vec[234]|float|void|int)\s+(\w+)\s*\(", text, flags=re.M):
            assert ident.startswith("prt_"), ident
    declared = set(re.findall(r"^uniform\s+\w+\s+(\w+)", shader_source("shading.glsl"), flags=re.M))
    uniforms = shader_uniforms(Lighting.from_sh(WHITE), Material())
    assert declared == set(uniforms)


def test_tonemap_ceiling_has_one_definition():
    # The GLSL gets shading.TONEMAP_MAX through the assembly's #define, never a copy of its own.
    for name in GLSL_FILES:
        assert "1.0e4" not in shader_source(name) and "10000" not in shader_source(name)
    assert GLSL_DEFINES["PRT_TONEMAP_MAX"] == TONEMAP_MAX
    assert f"#define PRT_TONEMAP_MAX {TONEMAP_MAX!r}\n" in glsl_source()
    assert not glsl_source().startswith("#version")


def test_assemble_fills_named_placeholders_and_refuses_missing_ones():
    source = assemble("packed_eval.frag", defines={"PRT_N": 3, "PRT_X": 0.1}, fills={"body": "void main() { f_out = vec4($x); }"})
    lines = source.splitlines()
    assert lines[:3] == ["#version 330", "#define PRT_N 3", "#define PRT_X 0.1"]
    assert source.count("#version") == 1 and "void main() { f_out = vec4($x); }" in source  # fills are not scanned
    with pytest.raises(KeyError, match="body"):
        assemble("packed_eval.frag")


def test_shader_uniforms_layout():
    rng = np.random.default_rng(12)
    lighting = Lighting.from_sh(rng.normal(size=(N_COEFFS, 3)))
    u = shader_uniforms(lighting, Material("glossy", albedo=(0.1, 0.2, 0.3), exponent=3.0))
    assert u["u_light"].shape == (16, 3) and u["u_light_matrix"].shape == (48, 16)
    assert all(value.dtype in (np.float32, np.int32) and value.flags.c_contiguous for value in u.values())
    # Element 16c + 4bi + bj is block (bi, bj) of M_c, column after column.
    for c in range(3):
        for bi in range(4):
            for bj in range(4):
                block = u["u_light_matrix"][16 * c + 4 * bi + bj].reshape(4, 4).T
                expected = lighting.light_matrix[c, 4 * bi : 4 * bi + 4, 4 * bj : 4 * bj + 4]
                np.testing.assert_allclose(block, expected, rtol=1e-6)
    lobe = sh.band_factors_to_coeff_scale(sh.phong_lobe(3.0))
    np.testing.assert_allclose(u["u_lobe"].ravel(), lobe, rtol=1e-7)
    assert int(u["u_material_kind"]) == MATERIAL_KINDS.index("glossy") == 1
    assert int(shader_uniforms(lighting, Material())["u_material_kind"]) == 0


def test_glsl_sh_basis_matches_numpy(gl_ctx):
    rng = np.random.default_rng(13)
    random_dirs = rng.normal(size=(4000, 3)) * rng.uniform(0.2, 5.0, size=(4000, 1))  # not unit length
    dirs = np.concatenate([np.eye(3), -np.eye(3), random_dirs])
    expected = sh.basis(dirs, BANDS)
    library = shader_source("sh_basis.glsl")
    # One run per vec4 of the result: run_fragment_program returns 4 values per row.
    main = "void main() {{ vec4 y[4]; prt_sh_basis(prt_input().xyz, y); f_out = y[{}]; }}"
    mains = [main.format(i) for i in range(4)]
    parts = [run_fragment_program(gl_ctx, library + main, dirs) for main in mains]
    got = np.concatenate(parts, axis=1)
    assert np.abs(got - expected).max() <= 1e-6


_SHADE_MAIN = """
uniform sampler2D u_t0;
uniform sampler2D u_t1;
uniform sampler2D u_t2;
uniform sampler2D u_t3;
uniform sampler2D u_normal;
uniform sampler2D u_view;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 t[4];
    t[0] = texelFetch(u_t0, p, 0);
    t[1] = texelFetch(u_t1, p, 0);
    t[2] = texelFetch(u_t2, p, 0);
    t[3] = texelFetch(u_t3, p, 0);
    f_out = vec4(prt_shade(t, texelFetch(u_normal, p, 0).xyz, texelFetch(u_view, p, 0).xyz), 1.0);
}
"""


def glsl_shade(ctx: moderngl.Context, uniforms: dict, T, normals, views) -> np.ndarray:
    """Run ``prt_shade`` once per row: T (N, 16), normals and views (N, 3) -> (N, 3) float32."""
    fragment = glsl_source() + _SHADE_MAIN  # assembled into packed_eval.frag (f_out) by the harness
    inputs = {f"u_t{i}": T[:, 4 * i : 4 * i + 4] for i in range(4)} | {"u_normal": normals, "u_view": views}
    return run_fragment_program(ctx, fragment, inputs, components=3, uniforms=uniforms)


@pytest.mark.parametrize("kind", MATERIAL_KINDS)
def test_glsl_shade_matches_numpy(gl_ctx, kind):
    rng = np.random.default_rng(14)
    count = 4096
    normals = rng.normal(size=(count, 3)) * rng.uniform(0.3, 3.0, size=(count, 1))
    views = rng.normal(size=(count, 3))
    # Partly shadowed unoccluded transfer plus noise: realistic magnitudes, every coefficient used.
    visible = rng.uniform(0.0, 1.0, size=(count, 1))
    T = unoccluded_transfer(normals) * visible + 0.1 * rng.normal(size=(count, N_COEFFS))
    material = Material(kind, albedo=(0.8, 0.5, 0.2), specular=(0.3, 0.6, 0.9), exponent=6.0)
    for lighting in (
        Lighting.from_envmap(bundled_envmap_path("studio"), rotation=random_rotation(rng)),
        Lighting.from_sh(rng.normal(size=(N_COEFFS, 3))),
    ):
        expected = shade(T, normals, views, lighting, material)
        got = glsl_shade(gl_ctx, shader_uniforms(lighting, material), T, normals, views)
        scale = np.abs(expected).max()
        assert scale > 0.1
        assert np.abs(got - expected).max() <= 1e-5 * scale


def test_glsl_tonemap_matches_numpy(gl_ctx):
    rng = np.random.default_rng(15)
    radiance = np.exp(rng.uniform(-8.0, 4.0, size=(3000, 3))).astype(np.float32)
    radiance[:4] = [[0.0, -1.0, np.nan], [np.inf, -np.inf, 1e30], [0.5, 1.0, 2.0], [1e-4, 3e-3, 8.0]]
    main = "void main() { f_out = vec4(prt_tonemap(prt_input().rgb, 1.5), 1.0); }"
    got = run_fragment_program(gl_ctx, glsl_source() + main, radiance)[:, :3]
    assert np.abs(got - tonemap(radiance, exposure=1.5)).max() <= 1e-5


def test_viewer_blit_tonemaps_like_numpy(gl_ctx):
    # The viewer window's program, assembled as the viewer does, run over an "image" of rows.
    radiance = np.exp(np.random.default_rng(16).uniform(-6.0, 3.0, size=(500, 3))).astype(np.float32)
    source = assemble("tonemap.glsl", "viewer_blit.frag", defines=GLSL_DEFINES)
    # one window pixel per texel (the harness lays 500 rows out as one 500x1 image)
    uniforms = {"u_exposure": np.float32(0.75), "u_window": np.array([len(radiance), 1], np.float32)}
    got = run_fragment_program(gl_ctx, source, {"u_image": radiance}, components=3, uniforms=uniforms)
    assert np.abs(got - tonemap(radiance, exposure=0.75)).max() <= 1e-5


# --------------------------------------------------------------------------- tone mapping


def test_tonemap_curve():
    x = np.linspace(0.0, 20.0, 20001)
    y = tonemap(np.repeat(x[:, None], 3, axis=1))
    assert y.dtype == np.float32 and y.shape == (x.size, 3)
    assert np.all(np.diff(y[:, 0]) >= 0)
    assert np.all(np.diff(y[x < 7.0, 0]) > 0)  # strictly increasing until it saturates
    assert y[0, 0] == 0.0
    assert tonemap(np.full((1, 1, 3), 1e38)).max() == 1.0
    assert (tonemap(np.array([[np.nan, np.inf, -np.inf], [-5.0, 0.0, 0.0]])) == 0).all()
    np.testing.assert_allclose(tonemap(np.full(3, 0.7), exposure=2.0), tonemap(np.full(3, 1.4)))
    assert linear_to_srgb(0.5) == pytest.approx(0.7354, abs=1e-4)
    assert linear_to_srgb(0.002) == pytest.approx(12.92 * 0.002)
    assert linear_to_srgb(1.0) == pytest.approx(1.0)
    srgb8 = to_srgb8(np.array([[0.0, 1e9, np.nan]]))
    assert srgb8.dtype == np.uint8 and srgb8.tolist() == [[0, 255, 0]]


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"kind": "metal"}, "kind"),
        ({"albedo": -0.1}, "albedo"),
        ({"albedo": (0.1, 0.2)}, "albedo"),
        ({"albedo": "red"}, "albedo"),
        ({"specular": (0.1, np.nan, 0.1)}, "specular"),
        ({"exponent": 0.0}, "exponent"),
        ({"exponent": np.inf}, "exponent"),
        ({"exponent": "shiny"}, "exponent"),
    ],
)
def test_material_validation_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=rf"Material\.{field}"):
        Material(**kwargs)


def test_material_defaults_and_broadcast():
    m = Material("glossy", albedo=0.5, specular=[0.1, 0.2, 0.3], exponent=4)
    assert m.albedo == (0.5, 0.5, 0.5) and m.specular == (0.1, 0.2, 0.3) and m.exponent == 4.0
    assert Material() == Material("diffuse")


def test_lighting_and_shade_validation_names_the_field():
    with pytest.raises(ValueError, match=r"Lighting\.sh"):
        Lighting.from_sh(np.zeros((5, 3)))
    with pytest.raises(ValueError, match=r"Lighting\.sh"):
        Lighting(np.full((16, 3), np.nan))
    with pytest.raises(ValueError, match="rotation"):
        Lighting.from_sh(WHITE, rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="rotation"):
        Lighting.from_sh(WHITE, rotation=np.eye(4))
    with pytest.raises(ValueError, match="bands"):
        shader_uniforms(Lighting.from_sh(np.zeros((9, 3))), Material())
    lighting = Lighting.from_sh(WHITE)
    with pytest.raises(ValueError, match="transfer"):
        shade(np.zeros((2, 9)), np.zeros((2, 3)), np.zeros((2, 3)), lighting, Material())
    with pytest.raises(ValueError, match="normals"):
        shade(np.zeros((2, 16)), np.zeros((3, 3)), np.zeros((2, 3)), lighting, Material())
    with pytest.raises(ValueError, match="view_dirs"):
        shade(np.zeros((2, 16)), np.zeros((2, 3)), np.zeros((2, 2)), lighting, Material())
    with pytest.raises(ValueError, match="exposure"):
        tonemap(np.zeros(3), exposure=-1.0)
