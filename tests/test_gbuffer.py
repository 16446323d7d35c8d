"""G-buffer pass and camera: surfaces, normals, segments, coverage, depth, no NaN.

Scenes are written by hand into tmp_path (no training pipeline): an icosphere mesh, the
same sphere as an SDF, the library SDF ``sphere_plane`` and a Cornell-like open box of
two-sided walls holding two closed boxes.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from prt.export.manifest import write_manifest
from prt.runtime.camera import Camera
from prt.runtime.errors import GeometryError
from prt.runtime.gbuffer import GBufferPass, segment_tables
from prt.runtime.manifest import load_manifest
from prt.runtime.segmentation import segment_of
from prt.train.sdf import SDF, Sphere, get_sdf

RADIUS = 0.6
SIZE = 65  # odd, so one pixel centre lies on the view axis
EYE = (0.0, 0.6, 3.2)

# Cornell-like room: open towards +z, walls at +-WALL, every wall its own object.
WALL = 0.9
FLOOR, CEILING, BACK, LEFT, RIGHT, SHORT_BOX, TALL_BOX = range(7)


# --------------------------------------------------------------------------- scene writing


def _segment(i: int, bounds) -> dict:
    return {
        "id": i,
        "kind": "analytic",
        "bounds": np.asarray(bounds, dtype=float).tolist(),
        "samples": 1,
        "validation": {"coeff_mae": 0.0, "shaded_mae": {}},
    }


def _write_scene(root: Path, geometry: dict, segmentation: dict, bounds: list) -> Path:
    """scene.json for ``geometry`` (whose file is already in ``root``); returns ``root``."""
    data = {
        "format": "prt-scene",
        "version": 1,
        "name": root.name,
        "sh_bands": 3,
        "geometry": geometry,
        "segmentation": segmentation,
        "segments": [_segment(i, b) for i, b in enumerate(bounds)],
        "lighting": {},
        "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]},
        "camera": {"eye": list(EYE), "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0},
    }
    write_manifest(root / "scene.json", data)
    return root


def _write_mesh(root: Path, vertices, faces, object_ids, two_sided, names) -> dict:
    root.mkdir(parents=True, exist_ok=True)
    np.savez(
        root / "geometry.npz",
        vertices=np.asarray(vertices, dtype=np.float32),
        faces=np.asarray(faces, dtype=np.uint32),
        object_ids=np.asarray(object_ids, dtype=np.int32),
        two_sided=np.asarray(two_sided, dtype=bool),
    )
    return {
        "type": "mesh",
        "file": "geometry.npz",
        "to_source": np.eye(4).tolist(),
        "triangles": len(faces),
        "objects": names,
    }


def _write_sdf(root: Path, sdf: SDF) -> dict:
    root.mkdir(parents=True, exist_ok=True)
    (root / "scene_sdf.glsl").write_text(sdf.glsl("scene_sdf"))
    return {"type": "sdf", "name": sdf.name, "glsl": "scene_sdf.glsl", "to_source": np.eye(4).tolist()}


# Sphere scenes: one object split at x = 0.1 into segments 0 (x <= 0.1) and 1.
SPHERE_SEGMENTATION = {
    "roots": {"0": 0},
    "nodes": [{"axis": 0, "split": 0.1, "left": 1, "right": 2}, {"leaf": 0}, {"leaf": 1}],
    "leaf_segment": [0, 1],
}
SPHERE_BOUNDS = [[[-1, -1, -1], [0.1, 1, 1]], [[0.1, -1, -1], [1, 1, 1]]]

BALL = SDF("ball", Sphere(center=(0.0, 0.0, 0.0), radius=RADIUS))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    """Folders of the test scenes, written once for the module."""
    base = tmp_path_factory.mktemp("gbuffer")
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    closed = np.zeros(len(sphere.faces))
    mesh = _write_mesh(base / "sphere_mesh", sphere.vertices, sphere.faces, closed, closed, ["ball"])
    out = {"sphere_mesh": _write_scene(base / "sphere_mesh", mesh, SPHERE_SEGMENTATION, SPHERE_BOUNDS)}
    sdf = _write_sdf(base / "sphere_sdf", BALL)
    out["sphere_sdf"] = _write_scene(base / "sphere_sdf", sdf, SPHERE_SEGMENTATION, SPHERE_BOUNDS)
    plane = _write_sdf(base / "sphere_plane", get_sdf("sphere_plane"))
    plane_seg = {
        "roots": {"0": 0},
        "nodes": [{"axis": 1, "split": -0.45, "left": 1, "right": 2}, {"leaf": 0}, {"leaf": 1}],
        "leaf_segment": [0, 1],
    }
    plane_bounds = [[[-1, -1, -1], [1, -0.45, 1]], [[-1, -0.45, -1], [1, 1, 1]]]
    out["sphere_plane"] = _write_scene(base / "sphere_plane", plane, plane_seg, plane_bounds)
    out["box"] = _write_box(base / "box", all_roots=True)
    out["box_no_root"] = _write_box(base / "box_no_root", all_roots=False)
    return out


def _quad(corners) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of the quad ``corners`` (4, 3), counter-clockwise seen from its front."""
    return np.asarray(corners, dtype=float), np.array([[0, 1, 2], [0, 2, 3]])


def _room_parts() -> list[tuple[np.ndarray, np.ndarray, int, bool]]:
    """(vertices, faces, object id, two-sided) of every object; walls face into the room.

    The boxes come first, so the walls behind them are drawn later: only the depth test
    keeps them hidden.
    """
    w = WALL
    parts = []
    for obj, extents, centre in (
        (SHORT_BOX, (0.5, 0.5, 0.5), (0.35, -w + 0.25, 0.2)),
        (TALL_BOX, (0.45, 1.1, 0.45), (-0.3, -w + 0.55, -0.35)),
    ):
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(centre)
        parts.append((np.asarray(box.vertices), np.asarray(box.faces), obj, False))
    walls = {
        FLOOR: [(-w, -w, -w), (-w, -w, w), (w, -w, w), (w, -w, -w)],  # normal +y
        CEILING: [(-w, w, -w), (w, w, -w), (w, w, w), (-w, w, w)],  # normal -y
        BACK: [(-w, -w, -w), (w, -w, -w), (w, w, -w), (-w, w, -w)],  # normal +z
        LEFT: [(-w, -w, -w), (-w, w, -w), (-w, w, w), (-w, -w, w)],  # normal +x
        RIGHT: [(w, -w, -w), (w, -w, w), (w, w, w), (w, w, -w)],  # normal -x
    }
    for obj, corners in walls.items():
        v, f = _quad(corners)
        parts.append((v, f, obj, True))
    # A zero-area triangle on the floor: must neither draw nor produce NaN.
    sliver = np.array([[0.0, -w, 0.0], [0.1, -w, 0.0], [0.2, -w, 0.0]])
    parts.append((sliver, np.array([[0, 1, 2]]), FLOOR, True))
    return parts


def _write_box(root: Path, all_roots: bool) -> Path:
    vertices, faces, ids, two_sided = [], [], [], []
    offset = 0
    for v, f, obj, open_surface in _room_parts():
        vertices.append(v)
        faces.append(f + offset)
        ids += [obj] * len(f)
        two_sided += [open_surface] * len(f)
        offset += len(v)
    names = ["floor", "ceiling", "back", "left", "right", "short", "tall"]
    mesh = _write_mesh(root, np.concatenate(vertices), np.concatenate(faces), ids, two_sided, names)
    # Floor split at x = 0 (segments 0, 1); back wall split at y = 0.2 then x = -0.3
    # (segments 2, 3, 4); every other object one leaf; the two boxes share segment 5.
    nodes = [
        {"axis": 0, "split": 0.0, "left": 1, "right": 2},  # 0 floor
        {"leaf": 0},
        {"leaf": 1},
        {"axis": 1, "split": 0.2, "left": 4, "right": 5},  # 3 back wall
        {"leaf": 2},
        {"axis": 0, "split": -0.3, "left": 6, "right": 7},
        {"leaf": 3},
        {"leaf": 4},
        {"leaf": 5},  # 8 ceiling
        {"leaf": 6},  # 9 left
        {"leaf": 7},  # 10 right
        {"leaf": 8},  # 11 short box
        {"leaf": 9},  # 12 tall box
    ]
    leaf_segment = [0, 1, 2, 3, 4, 5, 6, 7, 8, 8]
    roots = {FLOOR: 0, BACK: 3, CEILING: 8, LEFT: 9, RIGHT: 10, SHORT_BOX: 11, TALL_BOX: 12}
    if not all_roots:
        # The walls left and right lose their roots: the nearest-box rule decides.
        del roots[LEFT], roots[RIGHT]
    w = WALL
    bounds = [
        [[-w, -w, -w], [0, -w, w]],
        [[0, -w, -w], [w, -w, w]],
        [[-w, -w, -w], [w, 0.2, -w]],
        [[-w, 0.2, -w], [-0.3, w, -w]],
        [[-0.3, 0.2, -w], [w, w, -w]],
        [[-w, w, -w], [w, w, w]],
        [[-w, -w, -w], [-w, w, w]],
        [[w, -w, -w], [w, w, w]],
        [[-0.55, -w, -0.6], [0.6, 0.2, 0.45]],
    ]
    roots_json = {str(k): v for k, v in roots.items()}
    segmentation = {"roots": roots_json, "nodes": nodes, "leaf_segment": leaf_segment}
    return _write_scene(root, mesh, segmentation, bounds)


def _render(ctx, scene: Path, camera: Camera | None = None, width: int = SIZE, height: int = SIZE, **kwargs):
    """(GBuffer with depth, manifest, camera) of one frame."""
    manifest = load_manifest(scene)
    camera = camera or Camera.from_manifest(manifest)
    with GBufferPass(ctx, manifest, width, height, **kwargs) as gpass:
        gpass.render(camera)
        return gpass.read(depth=True), manifest, camera


def _assert_valid(g, camera: Camera) -> None:
    """No NaN/Inf; background zeros with segment -1; covered normals unit and facing the camera."""
    for name in ("position", "normal", "depth"):
        assert np.all(np.isfinite(getattr(g, name))), name
    c = g.covered
    assert np.all(g.position[~c] == 0.0) and np.all(g.normal[~c] == 0.0)
    assert np.all(g.segment[~c] == -1) and np.all(g.depth[~c] == 1.0)
    assert np.all(g.segment[c] >= 0)
    n, p = g.normal[c].astype(np.float64), g.position[c].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    to_eye = camera.eye - p
    assert np.all(np.einsum("ij,ij->i", n, to_eye) >= -1e-5 * np.linalg.norm(to_eye, axis=1))


def _reference_segments(g, manifest, object_id: int | np.ndarray = 0) -> np.ndarray:
    c = g.covered
    ids = np.broadcast_to(np.asarray(object_id), (int(c.sum()),))
    return segment_of(manifest, g.position[c].astype(np.float64), ids.astype(np.int64))


# --------------------------------------------------------------------------- camera


def test_camera_matrices_follow_opengl_conventions():
    cam = Camera((1.0, 2.0, 3.0), (0.2, -0.1, 0.3), up=(0.0, 1.0, 0.0), fov_y=50.0, near=0.1, far=20.0)
    view = cam.view()
    np.testing.assert_allclose(view[:3, :3] @ view[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(view @ [*cam.eye, 1.0], [0, 0, 0, 1], atol=1e-12)
    # The target lies straight ahead, down the camera's -Z axis.
    ahead = view @ [*cam.target, 1.0]
    np.testing.assert_allclose(ahead[:2], 0.0, atol=1e-12)
    assert ahead[2] < 0.0
    vp = cam.view_projection(1.5)
    for distance, ndc_z in ((cam.near, -1.0), (cam.far, 1.0)):
        clip = vp @ [*(cam.eye + distance * cam.forward), 1.0]
        np.testing.assert_allclose(clip[:3] / clip[3], [0.0, 0.0, ndc_z], atol=1e-9)


def test_ray_directions_pass_through_pixel_centres_top_row_first():
    cam = Camera(EYE, (0.1, 0.0, -0.2), fov_y=40.0)
    width, height = 9, 5
    rays = cam.ray_directions(width, height)
    assert rays.shape == (height, width, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=2), 1.0, atol=1e-12)
    np.testing.assert_allclose(rays[2, 4], cam.forward, atol=1e-12)
    assert rays[0, 4] @ cam.true_up > 0.0 > rays[-1, 4] @ cam.true_up
    assert rays[2, 0] @ cam.right < 0.0 < rays[2, -1] @ cam.right
    # Every ray projects back onto its own pixel centre.
    points = np.concatenate([cam.eye + rays, np.ones((height, width, 1))], axis=2)
    clip = points @ cam.view_projection(width / height).T
    ndc = clip[..., :2] / clip[..., 3:]
    col, row = np.meshgrid(np.arange(width), np.arange(height))
    np.testing.assert_allclose(ndc[..., 0], (col + 0.5) / width * 2 - 1, atol=1e-9)
    np.testing.assert_allclose(ndc[..., 1], 1 - (row + 0.5) / height * 2, atol=1e-9)


@pytest.mark.parametrize(
    "eye, target, up",
    [((0, 0, 1), (0, 0, 1), (0, 1, 0)), ((0, 2, 0), (0, 0, 0), (0, 1, 0)), ((0, 0, 3), (0, 0, 0), (0, 0, 0))],
    ids=["eye-is-target", "up-parallel", "up-zero"],
)
def test_camera_rejects_views_that_are_not_defined(eye, target, up):
    with pytest.raises(ValueError):
        Camera(eye, target, up)


def test_orbit_keeps_distance_and_from_manifest(scenes):
    cam = Camera.from_manifest(load_manifest(scenes["sphere_mesh"]).camera)
    np.testing.assert_allclose(cam.eye, EYE)
    assert cam.fov_y == 40.0
    for angle, axis in ((0.7, None), (-2.0, (1.0, 0.5, 0.0))):
        moved = cam.orbit(angle, axis)
        assert math.isclose(np.linalg.norm(moved.eye - moved.target), np.linalg.norm(cam.eye - cam.target))
        np.testing.assert_allclose(moved.target, cam.target)
    # A quarter turn about +Y takes an eye on +Z to +X.
    quarter = Camera((0, 0, 2), (0, 0, 0)).orbit(math.pi / 2)
    np.testing.assert_allclose(quarter.eye, (2, 0, 0), atol=1e-12)


# --------------------------------------------------------------------------- mesh and SDF surfaces


def test_mesh_sphere_positions_normals_and_background(gl_ctx, scenes):
    g, manifest, cam = _render(gl_ctx, scenes["sphere_mesh"])
    _assert_valid(g, cam)
    c = g.covered
    radius = np.linalg.norm(g.position[c], axis=1)
    # Vertices lie on the sphere; face interiors at most the chord sag inside it.
    assert radius.max() <= RADIUS + 1e-5 and radius.min() >= RADIUS - 1.5e-3
    radial = g.position[c] / radius[:, None]
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", g.normal[c], radial), -1, 1))).max() < 6.0
    # The centre pixel looks down the view axis at the point of the sphere nearest the eye.
    centre = SIZE // 2
    np.testing.assert_allclose(g.position[centre, centre], RADIUS * cam.forward * -1, atol=2e-3)
    assert not g.covered[0, 0] and g.segment[0, 0] == -1
    assert 0.15 < c.mean() < 0.5
    # Depth is GL's window depth of the position.
    clip = np.c_[g.position[c], np.ones(int(c.sum()))] @ cam.view_projection(1.0).T
    np.testing.assert_allclose(g.depth[c], 0.5 * clip[:, 2] / clip[:, 3] + 0.5, atol=1e-6)
    np.testing.assert_array_equal(g.segment[c], _reference_segments(g, manifest))
    assert set(np.unique(g.segment[c])) == {0, 1}


def test_sdf_scene_positions_on_surface(gl_ctx, scenes):
    sdf = get_sdf("sphere_plane")
    g, manifest, cam = _render(gl_ctx, scenes["sphere_plane"], width=96, height=80)
    _assert_valid(g, cam)
    c = g.covered
    p = g.position[c].astype(np.float64)
    assert np.abs(sdf.evaluate(p)).max() < 1e-3
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", g.normal[c], sdf.normals(p)), -1, 1)))
    assert np.percentile(angle, 99) < 2.0
    np.testing.assert_array_equal(g.segment[c], _reference_segments(g, manifest))
    assert set(np.unique(g.segment[c])) == {0, 1}
    assert not g.covered[0, 0]
    # Pixels are hit along their own camera rays.
    rays = cam.ray_directions(96, 80)[c]
    offset = p - cam.eye
    along = np.einsum("ij,ij->i", offset, rays)
    np.testing.assert_allclose(offset, along[:, None] * rays, atol=1e-4)


def test_mesh_and_sdf_sphere_agree(gl_ctx, scenes):
    cam = Camera((0.3, 0.8, 2.4), (0.0, 0.05, 0.0), fov_y=45.0)
    width, height = 96, 72  # not square, so the aspect ratio is exercised too
    mesh, _, _ = _render(gl_ctx, scenes["sphere_mesh"], cam, width, height)
    sdf, _, _ = _render(gl_ctx, scenes["sphere_sdf"], cam, width, height)
    _assert_valid(sdf, cam)
    # Tier 1: the masks differ only on pixels touching the silhouette.
    differ = mesh.covered != sdf.covered
    padded = np.pad(sdf.covered, 1, mode="edge")
    offsets = [(dy, dx) for dy in (0, 1, 2) for dx in (0, 1, 2)]
    shifted = [padded[dy : dy + height, dx : dx + width] for dy, dx in offsets]
    silhouette = np.any([s != sdf.covered for s in shifted], axis=0)
    assert not np.any(differ & ~silhouette)
    # Tier 2: few of them (the facets sit inside the true sphere).
    assert differ.sum() <= 0.1 * silhouette.sum()
    interior = mesh.covered & sdf.covered & ~silhouette
    np.testing.assert_allclose(mesh.position[interior], sdf.position[interior], atol=3e-3)
    np.testing.assert_allclose(mesh.depth[interior], sdf.depth[interior], atol=1e-4)
    np.testing.assert_array_equal(mesh.segment[interior], sdf.segment[interior])


# --------------------------------------------------------------------------- segments and faces


@pytest.mark.parametrize("scene", ["box", "box_no_root"])
def test_box_segments_match_reference(gl_ctx, scenes, scene):
    cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov_y=45.0)
    g, manifest, _ = _render(gl_ctx, scenes[scene], cam, 128, 128)
    _assert_valid(g, cam)
    c = g.covered
    # Which object each pixel shows is not in the G-buffer: recover it from the position.
    ids = _object_at(g.position[c].astype(np.float64), g.normal[c].astype(np.float64))
    np.testing.assert_array_equal(g.segment[c], segment_of(manifest, g.position[c].astype(np.float64), ids))
    assert len(np.unique(g.segment[c])) == 9


def _object_at(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Object of the room scene under each point: walls by plane, everything else a box."""
    w = WALL
    ids = np.where(p[:, 0] < 0.0, TALL_BOX, SHORT_BOX)
    on = lambda axis, value, normal: (np.abs(p[:, axis] - value) < 1e-4) & (n[:, axis] * normal > 0.99)
    for obj, axis, value, normal in (
        (FLOOR, 1, -w, 1), (CEILING, 1, w, -1), (BACK, 2, -w, 1), (LEFT, 0, -w, 1), (RIGHT, 0, w, -1),
    ):  # fmt: skip
        ids = np.where(on(axis, value, normal), obj, ids)
    return ids


def test_closed_front_faces_kept_back_faces_discarded(gl_ctx, scenes):
    g, _, cam = _render(gl_ctx, scenes["box"], Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov_y=45.0), 128, 128)
    # The short box's front face (z = 0.45) faces the camera and is drawn with its normal.
    front = g.covered & (np.abs(g.position[..., 2] - 0.45) < 1e-4)
    assert front.sum() > 100
    np.testing.assert_allclose(g.normal[front] @ np.array([0.0, 0.0, 1.0]), 1.0, atol=1e-6)
    # From inside the tall box its own faces are back faces: the room shows through.
    inside = Camera((-0.3, -0.4, -0.35), (-0.3, -0.4, -2.0), fov_y=30.0)
    g, _, _ = _render(gl_ctx, scenes["box"], inside, 64, 64)
    _assert_valid(g, inside)
    assert g.covered.all()
    np.testing.assert_allclose(g.position[..., 2], -WALL, atol=1e-4)


def test_two_sided_walls_seen_from_behind_face_the_camera(gl_ctx, scenes):
    behind = Camera((0.1, 0.2, -3.0), (0.0, 0.0, 0.0), fov_y=30.0)
    g, manifest, _ = _render(gl_ctx, scenes["box"], behind, 64, 64)
    _assert_valid(g, behind)
    # The back wall faces +z (into the room); seen from -z its normal must turn to -z.
    wall = g.covered & (np.abs(g.position[..., 2] + WALL) < 1e-4)
    assert wall.mean() > 0.5
    np.testing.assert_allclose(g.normal[wall] @ np.array([0.0, 0.0, -1.0]), 1.0, atol=1e-6)


def test_no_nan_inside_the_scene_or_looking_away(gl_ctx, scenes):
    inside = Camera((0.0, 0.1, 0.6), (0.2, -0.2, -1.0), fov_y=90.0)
    away = Camera((0.0, 0.0, 4.0), (0.0, 0.0, 9.0))
    for scene in ("box", "sphere_plane", "sphere_mesh", "sphere_sdf"):
        g, _, _ = _render(gl_ctx, scenes[scene], inside, 48, 40)
        _assert_valid(g, inside)
        g, _, _ = _render(gl_ctx, scenes[scene], away, 48, 40)
        _assert_valid(g, away)
        assert not g.covered.any()
    # Inside the SDF sphere (a closed solid): rays pass out through it, as the mesh's back faces.
    centre = Camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y=60.0)
    for scene in ("sphere_mesh", "sphere_sdf"):
        g, _, _ = _render(gl_ctx, scenes[scene], centre, 32, 32)
        _assert_valid(g, centre)
        assert not g.covered.any()


# --------------------------------------------------------------------------- read-back and API


def test_read_packed_matches_read_and_textures(gl_ctx, scenes):
    manifest = load_manifest(scenes["sphere_plane"])
    cam = Camera.from_manifest(manifest)
    width, height = 40, 24
    with GBufferPass(gl_ctx, manifest, width, height) as gpass:
        gpass.render(cam)
        g = gpass.read()
        packed = gpass.read_packed().reshape(height, width, 8)
        mine = np.empty((height * width, 8), dtype=np.float32)
        assert gpass.read_packed(out=mine) is mine
        texture = np.frombuffer(gpass.position_texture.read(), dtype=np.float32).reshape(height, width, 4)
        assert gpass.position_texture.size == gpass.normal_texture.size == (width, height)
    np.testing.assert_array_equal(mine.reshape(height, width, 8), packed)
    np.testing.assert_array_equal(packed[..., :3], g.position)
    np.testing.assert_array_equal(packed[..., 3] > 0.5, g.covered)
    np.testing.assert_array_equal(packed[..., 4:7], g.normal)
    np.testing.assert_array_equal(packed[..., 7].astype(np.int32), g.segment)
    np.testing.assert_array_equal(texture[::-1, :, :3], g.position)  # GL rows run bottom-up
    # Row 0 is the top: the upper half shows higher points than the lower half.
    top, bottom = g.covered[: height // 2], g.covered[height // 2 :]
    assert g.position[: height // 2][top, 1].mean() > g.position[height // 2 :][bottom, 1].mean()


def test_release_is_final_and_idempotent(gl_ctx, scenes):
    manifest = load_manifest(scenes["sphere_mesh"])
    gpass = GBufferPass(gl_ctx, manifest, 16, 16)
    gpass.release()
    gpass.release()
    with pytest.raises(RuntimeError):
        gpass.render(Camera.from_manifest(manifest))


def test_bad_mesh_file_is_a_geometry_error(gl_ctx, scenes, tmp_path):
    manifest = load_manifest(scenes["sphere_mesh"])
    bad = tmp_path / "bad.npz"
    np.savez(bad, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 5]], np.uint32))
    manifest.geometry.path = bad
    with pytest.raises(GeometryError, match="outside"):
        GBufferPass(gl_ctx, manifest, 8, 8)


def test_segment_tables_round_splits_down_to_float32(scenes):
    tables = segment_tables(load_manifest(scenes["sphere_mesh"]))
    split = tables["nodes"][0, 1]
    assert split.dtype == np.float32 and float(split) <= 0.1 < float(np.nextafter(split, np.float32(1)))
    np.testing.assert_array_equal(tables["nodes"][1], [-1, 0, 0, 0])
    np.testing.assert_array_equal(tables["roots"], [0])


def _containing_face(mesh, points):
    """(face index, barycentric coordinates) of each point: the face whose plane is nearest
    among those containing its projection (brute force: a coarse mesh, no rtree needed)."""
    tris = np.asarray(mesh.triangles)  # (F, 3, 3)
    normal = np.asarray(mesh.face_normals)
    best = np.full(len(points), np.inf)
    face = np.zeros(len(points), dtype=np.int64)
    bary = np.zeros((len(points), 3))
    for f in range(len(tris)):
        b = trimesh.triangles.points_to_barycentric(np.repeat(tris[f][None], len(points), 0), points)
        dist = np.abs((points - tris[f, 0]) @ normal[f])
        take = (b.min(axis=1) > -1e-4) & (dist < best)
        best[take], face[take], bary[take] = dist[take], f, b[take]
    assert np.isfinite(best).all()
    return face, bary


def test_training_samples_get_the_normals_the_gbuffer_interpolates(gl_ctx, tmp_path):
    """The networks learn transfer for the normals the runtime will ask about.

    On a coarse sphere the G-buffer's smooth normals differ from the face normals by several
    degrees; training samples (face + barycentric coordinates) must get the G-buffer's normal,
    not the face's, and the G-buffer must agree with the shared helper at its own pixels.
    """
    from prt.runtime.normals import corner_normals, interpolated_normals
    from prt.train.inputs.geometry import load_geometry
    from prt.train.inputs.sampling import sample_surface

    coarse = trimesh.creation.icosphere(subdivisions=1, radius=RADIUS)
    closed = np.zeros(len(coarse.faces))
    root = tmp_path / "coarse"
    mesh = _write_mesh(root, coarse.vertices, coarse.faces, closed, closed, ["ball"])
    g, _, _ = _render(gl_ctx, _write_scene(root, mesh, SPHERE_SEGMENTATION, SPHERE_BOUNDS))
    face, corner = corner_normals(coarse.vertices, coarse.faces)
    c = g.covered
    tri, bary = _containing_face(coarse, g.position[c].astype(np.float64))
    expected = interpolated_normals(corner, face, tri, bary)
    angle = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", g.normal[c], expected), -1, 1)))
    assert np.percentile(angle, 99) < 0.5
    flat = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", g.normal[c], face[tri]), -1, 1)))
    assert flat.mean() > 3.0  # the test can tell the two apart

    obj = tmp_path / "coarse.obj"
    coarse.export(obj)
    geometry = load_geometry(obj, normalise=False)
    samples = sample_surface(geometry, 4000, seed=0)
    gm = geometry.mesh
    face, corner = corner_normals(np.asarray(gm.vertices), np.asarray(gm.faces))
    bary = trimesh.triangles.points_to_barycentric(gm.triangles[samples.face_index], samples.points.astype(np.float64))
    expected = interpolated_normals(corner, face, samples.face_index, bary)
    cos = np.einsum("ij,ij->i", samples.normals, expected)
    assert cos.min() > 1.0 - 1e-5
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", samples.normals, face[samples.face_index]), -1, 1))).mean() > 3.0
