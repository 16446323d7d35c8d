"""Issue 43's benchmark pieces: the L2 SH probe grid baseline, --cameras, --exposure auto, the leak figure."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.bench import cli
from prt.bench.cameras import load_views
from prt.bench.exposure import KEY, auto_exposure
from prt.bench.leak import DARK, LIT, leak_figures, mean_leak
from prt.bench.probe_grid import (
    IRRADIANCE_BANDS, PROBE_BYTES, ProbeGrid, bake_probes, equal_bytes_spacing, grid_layout, lookup_reference, sphere_directions,
)  # fmt: skip
from prt.runtime import sh
from prt.runtime.errors import InputError

# ----------------------------------------------------------------------------- probe grid


def _random_grid(rng, dims=(3, 4, 2), invalid=0.3) -> ProbeGrid:
    valid = rng.uniform(size=dims) > invalid
    valid[0, 0, 0] = False
    return ProbeGrid(rng.normal(size=3), 0.37, rng.normal(size=dims + (9, 3)).astype(np.float32), valid, normal_bias=0.25)


def test_trilinear_lookup_matches_its_plain_twin():
    rng = np.random.default_rng(1)
    grid = _random_grid(rng)
    lo, hi = grid.origin - 0.3, grid.origin + 0.37 * (np.array(grid.dims) - 1) + 0.3  # points outside the grid too
    points = rng.uniform(lo, hi, size=(300, 3))
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # the corner of 8 invalid probes: the plain weights are kept
    grid.valid[:2, :2, :2] = False
    points[:5] = grid.origin + 0.1
    np.testing.assert_allclose(grid.lookup(points, normals), lookup_reference(grid, points, normals), rtol=1e-10, atol=1e-10)
    # an invalid probe takes no weight where a valid one is among the 8
    only = ProbeGrid(np.zeros(3), 1.0, np.zeros((2, 2, 2, 9, 3), dtype=np.float32), np.ones((2, 2, 2), dtype=bool), normal_bias=0.0)
    only.coefficients[1, 1, 1] = 1.0
    only.valid[1, 1, 1] = False
    assert np.abs(only.lookup(np.array([[0.9, 0.9, 0.9]]), np.array([[0.0, 1.0, 0.0]]))).max() == 0.0
    only.valid[1, 1, 1] = True
    assert only.lookup(np.array([[0.9, 0.9, 0.9]]), np.array([[0.0, 1.0, 0.0]]))[0, 0, 0] == pytest.approx(0.9**3)


def test_grid_layout_covers_the_bounds_and_equal_bytes_fits_the_budget():
    lo, hi = np.array([-1.0, -0.5, -1.0]), np.array([1.0, 0.5, 1.0])
    origin, dims = grid_layout(lo, hi, 0.25)
    assert list(dims) == [8, 4, 8]  # cell centres: a probe half a spacing inside each face of the bounds
    np.testing.assert_allclose(origin, lo + 0.125)
    np.testing.assert_allclose(origin + 0.25 * (dims - 1), hi - 0.125)
    for spacing in (0.3, 0.45, 0.7, 3.0):
        origin, dims = grid_layout(lo, hi, spacing)
        inset = np.concatenate([origin - lo, hi - (origin + spacing * (dims - 1))])
        assert np.all(dims >= 2) and np.allclose(inset[:3], inset[3:])
        more = np.tile(dims, 2) > 2  # (two probes per axis is the floor: a coarse spacing may put them outside)
        assert np.all(inset[more] >= spacing / 4 - 1e-12) and np.all(inset[more] <= 3 * spacing / 4 + 1e-12), (spacing, inset)
    for budget in (500, 10_000, 200_000):
        spacing = equal_bytes_spacing(lo, hi, budget)
        n = int(np.prod(grid_layout(lo, hi, spacing)[1]))
        assert n * PROBE_BYTES + math.ceil(n / 8) <= budget or n == 8
        denser = int(np.prod(grid_layout(lo, hi, spacing * 0.9)[1]))
        assert denser * PROBE_BYTES + math.ceil(denser / 8) > budget  # the finest spacing that fits, within 10 %


class _EmptyScene:
    """A tracer whose rays all leave the scene."""

    _triangles = np.zeros((1, 3, 3), dtype=np.float32)

    class _scene:  # noqa: N801
        @staticmethod
        def run(origins, dirs, output=1):
            n = len(origins)
            return {"primID": np.full(n, -1), "tfar": np.full(n, np.inf, dtype=np.float32), "Ng": np.zeros((n, 3), dtype=np.float32)}


def test_an_unoccluded_probe_gives_the_lights_diffuse_shading():
    """The cosine lobe has no band 3: an unoccluded L2 probe shades exactly as the 16-coefficient light's
    unoccluded transfer, dot(T, L) with T = (A_l / pi) Y_l(n)."""
    rng = np.random.default_rng(2)
    light = rng.normal(size=(16, 3))
    light[0] += 4.0
    coefficients, back = bake_probes(_EmptyScene(), np.zeros(1, dtype=bool), np.zeros((1, 3)), light, rays=4096, seed=0)
    assert back[0] == 0.0
    grid = ProbeGrid(np.zeros(3), 1.0, np.repeat(coefficients, 8, axis=0).reshape(2, 2, 2, 9, 3), np.ones((2, 2, 2), dtype=bool))
    normals = sphere_directions(50)
    expected = np.einsum("nk,kc->nc", sh.basis(normals, 3) * IRRADIANCE_BANDS, light[:9])
    np.testing.assert_allclose(grid.irradiance(np.full((50, 3), 0.5), normals), expected, atol=2e-2 * np.abs(expected).max())


def _box_tracer(inward: bool):
    import trimesh

    from prt.train.inputs.geometry import Geometry
    from prt.train.transport.transfer import make_tracer

    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    faces = np.asarray(box.faces)[:, ::-1] if inward else np.asarray(box.faces)
    mesh = trimesh.Trimesh(np.asarray(box.vertices), faces, process=False)
    n = len(faces)
    geometry = Geometry(mesh=mesh, object_ids=np.zeros(n, dtype=np.int64), object_names=["box"], two_sided=np.zeros(n, dtype=bool),
                        to_source=np.eye(4), source="box", sdf=None)  # fmt: skip
    return make_tracer(geometry), geometry


def test_a_probe_inside_a_solid_is_invalid_and_hits_carry_their_radiance():
    inside = np.array([[0.1, -0.2, 0.3]])
    tracer, geometry = _box_tracer(inward=False)  # a closed solid: the probe sees back faces only
    _, back = bake_probes(tracer, geometry.two_sided, inside, np.eye(16, 3), rays=256)
    assert back[0] == 1.0
    tracer, geometry = _box_tracer(inward=True)  # a closed room: front faces, each sending radiance (1, 2, 3)
    coefficients, back = bake_probes(tracer, geometry.two_sided, inside, np.eye(16, 3), rays=1024,
                                     hit_radiance=lambda q, n, f: np.tile([1.0, 2.0, 3.0], (len(q), 1)))  # fmt: skip
    assert back[0] == 0.0
    grid = ProbeGrid(np.zeros(3), 1.0, np.repeat(coefficients, 8, axis=0).reshape(2, 2, 2, 9, 3), np.ones((2, 2, 2), dtype=bool))
    normals = sphere_directions(20)
    np.testing.assert_allclose(grid.irradiance(np.zeros((20, 3)), normals), np.tile([1.0, 2.0, 3.0], (20, 1)), rtol=1e-3)


# ----------------------------------------------------------------------------- exposure, leak


def test_auto_exposure_puts_the_log_average_of_the_covered_pixels_on_the_key():
    image = np.zeros((4, 4, 3))
    image[:2] = 0.5
    covered = np.zeros((4, 4), dtype=bool)
    covered[:2] = True
    assert auto_exposure(image, covered) == pytest.approx(KEY / (1e-4 + 0.5))
    assert auto_exposure(image, np.zeros((4, 4), dtype=bool)) == 1.0  # nothing covered
    assert auto_exposure(np.zeros((4, 4, 3)), covered) == 1.0  # only black
    assert auto_exposure(image * 1e-3, covered) > 100.0  # an interior: a large gain
    with pytest.raises(InputError):
        auto_exposure(image, covered[:2])


def test_the_leak_figure_counts_light_where_the_reference_is_dark():
    ref = np.full((2, 4), 1.0)
    ref[0] = 0.0  # 4 dark pixels
    covered = np.ones((2, 4), dtype=bool)
    image = np.zeros((2, 4, 3))
    image[1] = 1.0
    assert leak_figures(image, ref, KEY, covered) == {"leak": 0.0, "leak_error": 0.0}
    image[0, :2] = 1.2 * LIT  # above LIT in key units (exposure KEY: radiance 1 is the key)
    image[0, 2] = 0.45 * DARK  # light, but not above LIT: only its excess counts
    f = leak_figures(image, ref, KEY, covered)
    assert f["leak"] == pytest.approx(0.5) and f["leak_error"] == pytest.approx((2 * 1.2 * LIT + 0.45 * DARK) / 4)
    f = leak_figures(image, ref, KEY / 10, covered)  # a tenth of the exposure: nothing is lit above LIT
    assert f["leak"] == 0.0
    assert leak_figures(image, np.ones((2, 4)), KEY, covered) == {"leak": None, "leak_error": None}  # no dark pixels
    assert mean_leak([{"leak": None, "leak_error": None}, {"leak": 0.5, "leak_error": 0.25}]) == {"leak": 0.5, "leak_error": 0.25}


# ----------------------------------------------------------------------------- --cameras


@pytest.mark.parametrize("content,field", [
    ("[]", "a views file must be a JSON object"),
    ('{"views": []}', "views: expected a non-empty list"),
    ('{"views": [{"eye": [0, 0, 3]}]}', "views[0].target: missing"),
    ('{"views": [{"eye": [0, 0, 3], "target": [0, 0, "a"]}]}', "views[0].target: expected 3 numbers"),
    ('{"views": [{"eye": [0, 0, 3], "target": [0, 0, 0], "fov": 200}]}', "views[0].fov: expected a number of degrees"),
    ('{"views": [{"eye": [0, 0, 3], "target": [0, 0, 0]}, {"eye": [1, 1, 1], "target": [1, 1, 1]}]}', "views[1]: eye and target coincide"),
    ('{"views": [{"eye": [0, 0, 3], "target": [0, 0, 0], "roll": 1}]}', "views[0].roll: unknown field"),
    ('{"views": [{"eye": [0, 0, 3], "target": [0, 0, 0], "up": [0, 0, 1]}]}', "views[0]: up [0.0, 0.0, 1.0] is zero or parallel"),
    ('{"views": [', "not valid JSON"),
    ('{"views": [{"eye": [0, 0, NaN], "target": [0, 0, 0]}]}', "not valid JSON"),
])  # fmt: skip
def test_a_malformed_views_file_is_one_line_naming_the_file_and_field(tmp_path, capsys, content, field):
    path = tmp_path / "views.json"
    path.write_text(content)
    with pytest.raises(InputError) as info:
        load_views(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and field in message and "\n" not in message, message
    assert cli.main([str(tmp_path / "scene.json"), "--cameras", str(path)]) == 2  # before the scene is even looked at
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and field in err[0] and str(path) in err[0]


def test_a_views_file_gives_its_cameras(tmp_path):
    path = tmp_path / "views.json"
    path.write_text(json.dumps({"views": [{"eye": [0, 0.2, -0.5], "target": [0, 0.2, 0.5], "fov": 70},
                                          {"eye": [1, 1, 3], "target": [0, 0, 0], "fov": 30, "up": [0, 1, 0]}]}))  # fmt: skip
    cameras = load_views(path)
    assert [c.fov_y for c in cameras] == [70.0, 30.0]
    assert np.allclose(cameras[0].eye, [0, 0.2, -0.5]) and np.allclose(cameras[1].target, 0.0)


# ----------------------------------------------------------------------------- a room, end to end

ROOM = 4.0  # metres: the room is 4 x 3 x 4, its window 1.6 x 1 in the +z wall; a ground 12 m wide around it


def _room_obj(path: Path) -> None:
    """A closed box room (walls facing inward) with a window hole, on a ground plane outside."""
    v, f = [], []

    def quad(a, b, c, d, normal):  # the side ``normal`` points to is the front
        a, b, c, d = (np.array(p, dtype=float) for p in (a, b, c, d))
        if np.dot(np.cross(b - a, c - b), normal) < 0:
            a, b, c, d = d, c, b, a
        base = len(v) + 1
        v.extend([a, b, c, d])
        f.append((base, base + 1, base + 2))
        f.append((base, base + 2, base + 3))

    h, s = 3.0, ROOM / 2
    lines = ["o ground"]
    g = 3 * ROOM / 2
    quad((-g, -0.02, g), (g, -0.02, g), (g, -0.02, -g), (-g, -0.02, -g), (0, 1, 0))
    lines += [f"v {x} {y} {z}" for x, y, z in v] + [f"f {a} {b} {c}" for a, b, c in f]
    v.clear(), f.clear()
    quad((-s, 0, -s), (s, 0, -s), (s, 0, s), (-s, 0, s), (0, 1, 0))  # floor
    quad((-s, h, -s), (-s, h, s), (s, h, s), (s, h, -s), (0, -1, 0))  # ceiling
    quad((-s, 0, -s), (-s, h, -s), (s, h, -s), (s, 0, -s), (0, 0, 1))  # -z wall
    quad((-s, 0, -s), (-s, 0, s), (-s, h, s), (-s, h, -s), (1, 0, 0))  # -x wall
    quad((s, 0, -s), (s, h, -s), (s, h, s), (s, 0, s), (-1, 0, 0))  # +x wall
    wx, y0, y1 = 0.8, 1.0, 2.0  # the +z wall around its window
    for a, b, c, d in (((-s, 0, s), (-s, y0, s), (s, y0, s), (s, 0, s)), ((-s, y1, s), (-s, h, s), (s, h, s), (s, y1, s)),
                       ((-s, y0, s), (-s, y1, s), (-wx, y1, s), (-wx, y0, s)), ((wx, y0, s), (wx, y1, s), (s, y1, s), (s, y0, s))):
        quad(a, b, c, d, (0, 0, -1))
    base = 4
    lines += ["o room"] + [f"v {x} {y} {z}" for x, y, z in v] + [f"f {a + base} {b + base} {c + base}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    out = tmp_path_factory.mktemp("room")
    _room_obj(out / "room.obj")
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(out / "room.obj"), "-o", str(out / "scene"), "--samples", "8000",
         "--validation", "1000", "--rays", "64", "--segments", "1", "--hidden", "16", "--layers", "2", "--steps", "100",
         "--bounces", "0", "--no-analytic", "--no-progress", "--threads", "1"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out / "scene" / "scene.json"


def _inside_views(scene_json: Path) -> list[dict]:
    """Two views inside the room, looking at the window wall and along it, in normalised space."""
    to_source = np.asarray(json.loads(scene_json.read_text())["geometry"]["to_source"], dtype=np.float64)
    from_source = np.linalg.inv(to_source)

    def n(p):
        return [float(x) for x in (from_source @ np.array([*p, 1.0]))[:3]]

    return [{"eye": n((0.3, 1.4, -1.6)), "target": n((0.0, 1.2, 2.0)), "fov": 75.0},
            {"eye": n((-1.5, 1.8, 0.5)), "target": n((1.5, 0.8, 1.9)), "fov": 60.0}]  # fmt: skip


@pytest.mark.gl
def test_the_probe_grid_leaks_into_a_closed_room_and_the_reference_does_not(room, tmp_path, gl_ctx, capsys):
    views = tmp_path / "views.json"
    views.write_text(json.dumps({"views": _inside_views(room)}))
    out = tmp_path / "r.json"
    argv = [str(room), "--cameras", str(views), "--size", "40", "--ref-rays", "512", "--ref-rays-max", "512", "--baseline-rays", "64",
            "--warmup", "1", "--gemm-size", "128", "--precisions", "fp32", "--backends", "onnx", "vertex", "probes",
            "--exposure", "auto", "--json", str(out), "--md", str(tmp_path / "r.md")]  # fmt: skip
    assert cli.main(argv) == 0
    report = json.loads(out.read_text())
    scene = report["scenes"][0]
    assert scene["views_from"] == str(views) and scene["exposure"] == "auto"
    records = {r["label"]: r for r in report["records"]}
    assert {"probes equal-bytes diffuse", "probes engine diffuse", "onnx fp32 diffuse", "vertex diffuse"} <= set(records)
    assert all(r["views"] == 2 for r in report["records"])
    # --cameras renders the given views: the records' covered pixels are those of the file's cameras
    from prt.runtime.camera import Camera
    from prt.runtime.renderer import Renderer, Scene

    covered = []
    with Renderer(Scene.load(room), 40, 40, backend="onnx", ctx=gl_ctx) as renderer:
        for v in _inside_views(room):
            renderer.set_camera_object(Camera(v["eye"], v["target"], (0, 1, 0), v["fov"]))
            covered.append(int(renderer.gbuffer_image().covered.sum()))
    assert records["vertex diffuse"]["covered_pixels"] == float(np.median(covered))
    assert min(covered) > 0.8 * 40 * 40  # inside the room: walls, floor, ceiling, and through the window the ground or the sky
    # light leaking: the reference's second seed puts no light where the first is dark; the probe grid does
    floor = scene["reference"]["leak"]["40x40"]["diffuse"]
    assert floor["leak"] is not None and floor["leak"] <= 0.02, floor
    for density in ("equal-bytes", "engine"):  # probes outside the room light the window wall's dark inside
        leak = records[f"probes {density} diffuse"]["leak"]
        assert leak > floor["leak"] + 0.1 and leak > 10 * floor["leak"], (density, leak, floor)
    assert records["probes engine diffuse"]["leak"] > 0.5
    assert records["vertex diffuse"]["leak"] <= floor["leak"] + 0.02  # per-vertex visibility: no light through the wall
    probes = records["probes equal-bytes diffuse"]
    assert probes["probe_grid"]["density"] == "equal-bytes" and probes["weight_bytes"] <= max(scene["weight_bytes"], 8 * PROBE_BYTES + 1)
    assert scene["probe_grid"]["mitigation"].startswith("probe validity")
    md = (tmp_path / "r.md").read_text()
    assert "light leaking" in md and "probes equal-bytes diffuse" in md
    # a view that sees nothing of the scene: one line naming the file and the view, the scene left out, exit 2
    views.write_text(json.dumps({"views": [_inside_views(room)[0], {"eye": [0, 0, 30], "target": [0, 0, 60], "fov": 40}]}))
    assert cli.main([*argv[:-4], "--json", str(tmp_path / "none.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{views}: views[1] sees no part of the scene" in err[0], err


@pytest.mark.gl
def test_probes_with_bounces_match_the_references_brightness(cornell_rgb, tmp_path, gl_ctx):
    """The Cornell box with 2 bounces (every wall's light partly interreflected): the probe grid's frame
    carries the reference's brightness on average, floor, ceiling and walls alike (the hits' radiance
    with one bounce less, from the nearest independent sample), where the direct light alone is over 10 %
    darker: a grid whose hits sent nothing, or too much, fails."""
    from prt.bench.probe_bench import probe_frame, scene_grids
    from prt.bench.reference import shade_image
    from prt.bench.scene_bench import SceneBench, Settings
    from prt.runtime.renderer import Renderer

    settings = Settings(views=1, sizes=(32,), ref_rays=64, ref_hit_rays=32, precisions=("fp32",), backends=("probes",), cache=tmp_path)
    sb = SceneBench(cornell_rgb, settings, gl_ctx, 1.0, lambda *_: None)
    with Renderer(sb.scene, 32, 32, backend="onnx", ctx=gl_ctx) as base:
        grids, entry = scene_grids(sb, base.lighting)
        assert entry["samples"] > 0 and set(grids) == {"equal-bytes", "engine"}
        camera = sb.cameras[0]
        base.set_camera_object(camera)
        g = base.gbuffer_image()
        covered = g.covered
        traced = sb.source.trace("probe-test", g.position[covered], g.normal[covered], 64, 32, 0)
        diffuse = sb.materials["diffuse"]
        reference = shade_image(sb.source.combine(traced["direct"], traced["indirect"]), g, camera.eye, base.lighting, diffuse)
        direct_only = shade_image(traced["direct"], g, camera.eye, base.lighting, diffuse)
        image, _ = probe_frame(grids["equal-bytes"], base.gbuffer, camera, diffuse.albedo, 32, 32)
    ref, probes, direct = reference[covered].mean(), image[covered].mean(), direct_only[covered].mean()
    assert ref > 1.1 * direct  # the bounces matter here
    assert abs(probes / ref - 1.0) < 0.5 * (ref / direct - 1.0), (probes, ref, direct)
