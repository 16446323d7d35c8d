"""Interreflection end to end (issue 13): ``prt-train --bounces N``, RGB transfer in the networks,
the manifest's ``interreflection``, both backends and both shadings.

One tiny Cornell box build (its MTL colours, 2 bounces, a few hundred training steps) serves the
render tests; the rest need no build.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from prt.runtime.envmaps import bundled_envmap_path
from prt.runtime.errors import InputError, SpecError
from prt.runtime.gl import run_fragment_program
from prt.runtime.manifest import Manifest, load_manifest
from prt.runtime.shading import Lighting, Material, diffuse_light_matrix, glsl_source, shade, shader_uniforms

DATA = Path(__file__).resolve().parent / "data"
CORNELL = DATA / "CornellBox-Original.obj"
N = 16


# --------------------------------------------------------------------------- build side, no build


def test_spec_bounces_default_auto_and_checked():
    from prt.train.build import BuildSpec, spec_from_dict

    assert BuildSpec(geometry="x").bounces == "auto"  # as many as the scene needs (docs/benchmarks/bounce_depth.md)
    spec = BuildSpec(geometry="x", bounces=0)
    assert spec.layout == "direct"
    # N = 0: the architecture records (ONNX metadata, fit-cache keys) are those of before the
    # layouts existed, so a direct-only build writes the same bytes (checked by hand against the
    # previous commit: identical ONNX, GLSL, geometry and scene.json).
    from prt.train.networks.network import Architecture

    assert set(Architecture().as_dict()) == {"hidden", "layers", "pos_freqs", "normal_freqs", "bands", "input_dim"}
    assert all(a.layout == "direct" and "layout" not in a.as_dict() and a.outputs == 16 for a in spec.architectures())
    rgb = spec_from_dict({**spec.to_dict(), "bounces": 2})
    assert rgb.layout == "direct+rgb"
    assert all(a.outputs == 64 and a.as_dict()["outputs"] == 64 for a in rgb.architectures())
    for bad, message in ((-1, "bounces: expected 0 .. 16"), (17, "bounces: expected 0 .. 16"), (2.0, "bounces: expected int"),
                         (True, "bounces: expected int"), ("2", "bounces: expected int")):  # fmt: skip
        with pytest.raises(SpecError, match=message.replace(".", r"\.")):
            spec_from_dict({**spec.to_dict(), "bounces": bad})
    with pytest.raises(SpecError, match="bounce_rays: expected 1"):
        spec_from_dict({**spec.to_dict(), "bounces": 1, "bounce_rays": 0})


def test_total_transfer_error_is_that_of_the_rgb_transfer():
    from prt.train.networks.fit import total_transfer, transfer_error

    rng = np.random.default_rng(3)
    direct, indirect = rng.normal(size=(50, N)), rng.normal(size=(50, 3, N))
    packed = np.concatenate([direct, indirect.reshape(50, -1)], axis=1)
    total = total_transfer(packed, N)
    assert total.shape == (50, N, 3)
    np.testing.assert_allclose(total[:, :, 1], direct + indirect[:, 1])
    # An error in the direct part counts in all three channels; one in the indirect R part in one.
    shifted = packed.copy()
    shifted[:, 16 : 32] += 0.3
    assert transfer_error(shifted, packed, N) == pytest.approx(0.1)
    assert transfer_error(packed[:, :N] + 0.2, packed[:, :N], N) == pytest.approx(0.2)  # direct layout: as before


def test_bounce_stage_is_deterministic_and_resumes(tmp_path):
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.interreflection import bounce_stage
    from prt.train.inputs.sampling import sample_surface
    from prt.train.transport.transfer import compute_transfer

    geometry = load_geometry(str(CORNELL))
    train, valid = sample_surface(geometry, 1500, seed=0), sample_surface(geometry, 300, seed=0, stream=1)
    data = [{"points": s.points, "normals": s.normals, "transfer": compute_transfer(geometry, s.points, s.normals, rays=32, threads=2)}
            for s in (train, valid)]  # fmt: skip
    albedo = np.full((len(geometry.mesh.faces), 3), 0.5)
    run = lambda: bounce_stage(geometry.mesh, tmp_path / "cache", *data, albedo, 2, rays=16, seed=1, chunk_size=512, key="k",  # noqa: E731
                               threads=2, progress=False, log=lambda line: None)  # fmt: skip
    first = run()
    stores = sorted((tmp_path / "cache").glob("bounce-*"))
    # named with the rules (CLEAR_RULE, TRACE_RULE)
    assert [p.name for p in stores] == ["bounce-train-k-clear1-far2.5t32", "bounce-validation-k-clear1-far2.5t32"]
    assert len(list(stores[0].glob("chunk_*.npy"))) == 3 and len(list((stores[0] / "traced").glob("chunk_*.npy"))) == 3
    (stores[0] / "chunk_00001.npy").unlink()  # an interrupted run: that chunk is traced again
    (stores[1] / "chunk_00000.npy").write_bytes(b"damaged")
    (stores[0] / "traced" / "chunk_00002.npy").write_bytes(b"damaged")  # its traced transfer damaged: traced again
    second = run()
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)
    assert first[0].shape == (1500, N, 3) and first[1].shape == (300, N, 3)
    # Grey albedo: the indirect light is grey, and it is light (positive DC term) inside the box.
    assert np.allclose(first[0][:, :, 0], first[0][:, :, 2])
    assert first[0][:, 0].mean() > 0 and first[1][:, 0].mean() > 0


# --------------------------------------------------------------------------- shading twins


_SHADE_MAIN = "".join(f"uniform sampler2D u_t{k};\n" for k in range(16)) + """
uniform sampler2D u_normal;
uniform sampler2D u_view;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 t[4], tr[4], tg[4], tb[4];
    t[0] = texelFetch(u_t0, p, 0); t[1] = texelFetch(u_t1, p, 0); t[2] = texelFetch(u_t2, p, 0); t[3] = texelFetch(u_t3, p, 0);
    tr[0] = texelFetch(u_t4, p, 0); tr[1] = texelFetch(u_t5, p, 0); tr[2] = texelFetch(u_t6, p, 0); tr[3] = texelFetch(u_t7, p, 0);
    tg[0] = texelFetch(u_t8, p, 0); tg[1] = texelFetch(u_t9, p, 0); tg[2] = texelFetch(u_t10, p, 0); tg[3] = texelFetch(u_t11, p, 0);
    tb[0] = texelFetch(u_t12, p, 0); tb[1] = texelFetch(u_t13, p, 0); tb[2] = texelFetch(u_t14, p, 0); tb[3] = texelFetch(u_t15, p, 0);
    f_out = vec4(prt_shade_with_indirect(t, texelFetch(u_normal, p, 0).xyz, texelFetch(u_view, p, 0).xyz, u_albedo, u_specular,
                                         u_lobe, u_material_kind, prt_incident_rgb(tr, tg, tb)), 1.0);
}
"""


@pytest.mark.parametrize("kind", ["diffuse", "glossy"])
def test_glsl_shading_of_rgb_transfer_matches_numpy(gl_ctx, kind):
    rng = np.random.default_rng(13)
    count = 2048
    normals, views = rng.normal(size=(count, 3)), rng.normal(size=(count, 3))
    T = np.concatenate([0.3 * rng.normal(size=(count, N)), 0.05 * rng.normal(size=(count, 3 * N))], axis=1)
    lighting = Lighting.from_envmap(bundled_envmap_path("potsdamer"))
    material = Material(kind, albedo=(0.8, 0.5, 0.2), specular=(0.3, 0.6, 0.9), exponent=6.0)
    expected = shade(T, normals, views, lighting, material)
    inputs = {f"u_t{k}": T[:, 4 * k : 4 * k + 4] for k in range(16)} | {"u_normal": normals, "u_view": views}
    got = run_fragment_program(gl_ctx, glsl_source() + _SHADE_MAIN, inputs, components=3, uniforms=shader_uniforms(lighting, material))
    scale = np.abs(expected).max()
    assert scale > 0.1
    assert np.abs(got - expected).max() <= 1e-5 * scale
    # The indirect part matters here, and it enters as albedo_c * dot(T_ind_c, L_c).
    direct_only = shade(T[:, :N], normals, views, lighting, material)
    indirect = np.einsum("pcn,nc->pc", T[:, N:].reshape(count, 3, N), lighting.sh) * np.asarray(material.albedo)
    unclamped = (expected > 1e-6) & (direct_only > 1e-6)  # neither clamped at 0
    np.testing.assert_allclose(expected[unclamped], (direct_only + indirect)[unclamped], rtol=1e-4, atol=1e-5)
    assert np.abs(indirect).mean() > 0.01 * np.abs(direct_only).mean()


def test_diffuse_light_matrix_is_the_shading():
    rng = np.random.default_rng(5)
    T = rng.normal(size=(100, 4 * N))
    lighting = Lighting.from_sh(rng.normal(size=(N, 3)))
    albedo = (0.9, 0.4, 0.1)
    expected = shade(T, np.tile([0.0, 1.0, 0.0], (100, 1)), np.tile([0.0, 0.0, 1.0], (100, 1)), lighting, Material(albedo=albedo))
    np.testing.assert_allclose(np.maximum(T.astype(np.float32) @ diffuse_light_matrix(lighting, albedo, 4 * N), 0), expected, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(diffuse_light_matrix(lighting, albedo, N), (lighting.sh * np.asarray(albedo)).astype(np.float32))


# --------------------------------------------------------------------------- a built Cornell box


# cornell_rgb: the build of tests/conftest.py (2 bounces, tiny networks)


def test_manifest_records_the_bounces_and_round_trips(cornell_rgb):
    m = load_manifest(cornell_rgb)
    raw = json.loads(cornell_rgb.read_text())
    assert set(raw["interreflection"]) == {"bounces", "bounce_rays", "layout", "albedos"}
    assert (m.interreflection.bounces, m.interreflection.bounce_rays, m.interreflection.layout) == (2, 32, "direct+rgb")
    assert m.transfer_width == 64 and raw["version"] == 1  # an optional field: no version bump
    # The albedos that bounced are the mesh's own materials (Kd), as the manifest's materials record them.
    materials = {e["object"]: e["albedo"] for e in raw["materials"]}
    assert m.interreflection.albedos == {name: materials[name] for name in m.geometry.objects}
    assert m.interreflection.albedos["leftWall"] == [0.63, 0.065, 0.05]
    again = Manifest.from_dict(m.to_dict(), cornell_rgb)
    assert again.interreflection == m.interreflection
    assert m.to_dict()["interreflection"] == raw["interreflection"]
    # Without the field the same scene loads as direct-only (older manifests).
    assert Manifest.from_dict({k: v for k, v in raw.items() if k != "interreflection"}, cornell_rgb).transfer_width == 16
    bad = json.loads(json.dumps(raw))
    bad["interreflection"]["albedos"]["nosuchobject"] = [1, 1, 1]
    with pytest.raises(SpecError, match=r"interreflection\.albedos\.nosuchobject: 'nosuchobject' is not an object"):
        Manifest.from_dict(bad, cornell_rgb)
    bad["interreflection"] = {**raw["interreflection"], "layout": "rgb"}
    with pytest.raises(SpecError, match=r"interreflection\.layout"):
        Manifest.from_dict(bad, cornell_rgb)
    import onnx

    model = onnx.load(str(m.segments[0].model))
    assert model.graph.output[0].type.tensor_type.shape.dim[1].dim_value == 64


def test_backends_agree_bleed_colour_and_relight_without_networks(cornell_rgb):
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(cornell_rgb)
    images, transfers = {}, {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, 96, 96, backend=backend) as r:
            images[backend] = r.render()
            transfers[backend] = r.render_transfer()
            if backend == "onnx":
                gbuffer = r.gbuffer_image()
            calls = r.network_calls
            r.set_envmap(bundled_envmap_path("studio"))
            r.set_material("diffuse", albedo=(0.2, 0.9, 0.2), object="floor")
            relit = r.render()
            assert r.network_calls == calls  # relighting and a new receiver albedo run no network
            assert not np.allclose(relit, images[backend])
    a, g = images["onnx"], images["glsl"]
    assert transfers["onnx"].shape == (96, 96, 64)
    psnr = 10 * np.log10(a.max() ** 2 / max(float(np.mean((a - g) ** 2)), 1e-30))
    assert psnr >= 60, psnr
    # Colour bleeding: the floor next to the red (left) wall is redder than next to the green one.
    floor = gbuffer.covered & (gbuffer.normal[..., 1] > 0.9) & (gbuffer.position[..., 1] < gbuffer.position[..., 1][gbuffer.covered].min() + 0.05)
    x = gbuffer.position[..., 0]
    lo, hi = x[floor].min(), x[floor].max()
    near_red, near_green = floor & (x < lo + 0.25 * (hi - lo)), floor & (x > hi - 0.25 * (hi - lo))
    assert near_red.sum() > 20 and near_green.sum() > 20

    def red_over_green(mask):
        rgb = a[mask].mean(axis=0)
        return rgb[0] / rgb[1]

    assert red_over_green(near_red) > 1.05 * red_over_green(near_green)
    # The indirect part of the transfer carries it (its DC term): red over green falls from the red
    # wall to the green one, and exceeds 1 next to the red wall.
    indirect = transfers["onnx"][..., 16:].reshape(96, 96, 3, 16)[..., 0]
    ratio = [indirect[mask, 0].mean() / indirect[mask, 1].mean() for mask in (near_red, near_green)]
    assert ratio[0] > 1.2 and ratio[0] > 1.2 * ratio[1], ratio


def test_texture_backend_needs_a_transfer_texture(cornell_rgb):
    # RGB transfer textures themselves: tests/test_texture_bounces.py
    from prt.runtime.backends.texture import TextureBackend
    from prt.runtime.gl import create_context

    with pytest.raises(InputError, match="needs a mesh scene with a transfer_texture"):
        TextureBackend(create_context(), load_manifest(cornell_rgb))


def test_generated_glsl_of_rgb_networks_matches_onnx(cornell_rgb, gl_ctx):
    import onnxruntime as ort

    from prt.export.glsl import evaluate_glsl

    path = load_manifest(cornell_rgb).segments[0].model
    x = np.random.default_rng(0).uniform(-1, 1, (300, 6)).astype(np.float32)
    expected = ort.InferenceSession(str(path)).run(None, {"x": x})[0]
    assert expected.shape == (300, 64)
    for layout in ("const", "texture"):  # 16 vec4 blocks: read back 8 attachments at a time
        np.testing.assert_allclose(evaluate_glsl(gl_ctx, path, x, layout=layout), expected, atol=2e-6, rtol=1e-5)


def test_one_pass_and_two_draws_write_the_same_transfer(cornell_rgb, gl_ctx):
    """The 64-wide transfer in one draw (OpenGL 4.3: 8 targets + 8 image stores, the networks run once)
    against the 3.3 path's two draws of 8 targets, and both against ONNX Runtime (>= 60 dB)."""
    from prt.runtime.backends.glsl import GlslBackend
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(cornell_rgb)
    transfers, images = {}, {}
    for one_pass in (True, False):
        with Renderer(scene, 72, 64, backend="glsl", ctx=gl_ctx) as r:
            r._backends["glsl"] = GlslBackend(gl_ctx, scene.manifest, one_pass=one_pass)
            assert r._backend().one_pass is one_pass  # llvmpipe has OpenGL 4.5: the one-pass program links
            images[one_pass], transfers[one_pass] = r.render(), r.render_transfer()
    with Renderer(scene, 72, 64, backend="onnx", ctx=gl_ctx) as r:
        reference = r.render_transfer()
    assert transfers[True].shape == (64, 72, 64)
    np.testing.assert_allclose(transfers[True], transfers[False], rtol=1e-6, atol=1e-7)
    assert np.array_equal(images[True], images[False]) or np.abs(images[True] - images[False]).max() < 1e-6
    for t in transfers.values():
        mse = float(np.mean((t.astype(np.float64) - reference) ** 2))
        assert 10 * np.log10(np.abs(reference).max() ** 2 / max(mse, 1e-30)) >= 60
