"""How many bounces (issue 13): the truncation error of N bounces and ``prt-train --bounces auto``.

Twins: :func:`prt.train.transport.bounce_depth.truncation_errors` against a per-sample loop.  Analytic
expectations: on a convex object no bounce ray hits anything, so auto keeps 0 bounces; inside a
box open at the top the walls light each other, so auto keeps at least one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
trimesh = pytest.importorskip("trimesh")

from prt.runtime.envmap import load_envmap_sh  # noqa: E402
from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path  # noqa: E402
from prt.runtime.errors import SpecError  # noqa: E402
from prt.runtime.shading import tonemap  # noqa: E402
from prt.train.transport.bounce_depth import AUTO_MAX_BOUNCES, AUTO_PSNR, PSNR_CAP, auto_bounces, choose_bounces, truncation_errors  # noqa: E402


def _lights() -> dict:
    return {name: load_envmap_sh(bundled_envmap_path(name), 4) for name in BUNDLED_ENVMAPS}


def _plain_errors(direct, terms, albedo, light, exposure):
    """The truncation errors one sample, one channel, one term at a time."""
    count, n = direct.shape
    radiance = np.zeros((len(terms) + 1, count, 3))
    for s in range(count):
        for c in range(3):
            total = direct[s].astype(np.float64).copy()
            for k in range(len(terms) + 1):
                if k:
                    total = total + terms[k - 1][s, :, c]
                radiance[k, s, c] = max(0.0, albedo[s, c] * sum(total[j] * light[j, c] for j in range(n)))
    ref = radiance[-1]
    rel, psnr = [], []
    for k in range(len(terms)):
        rel.append(float(np.abs(radiance[k] - ref).sum() / ref.sum()))
        mse = float(((np.asarray(tonemap(radiance[k], exposure), np.float64) - np.asarray(tonemap(ref, exposure), np.float64)) ** 2).mean())
        psnr.append(PSNR_CAP if mse <= 10 ** (-PSNR_CAP / 10) else -10 * math.log10(mse))
    return rel, psnr


def test_truncation_errors_match_a_plain_loop():
    rng = np.random.default_rng(7)
    count, n = 40, 16
    direct = rng.normal(0.3, 0.2, size=(count, n))
    terms = [rng.normal(0.05 / (b + 1), 0.05, size=(count, n, 3)) for b in range(3)]
    albedo = rng.uniform(0.2, 0.9, size=(count, 3))
    lights = {"a": rng.normal(1.0, 0.5, size=(n, 3)), "b": rng.normal(0.5, 0.5, size=(n, 3))}
    errors = truncation_errors(direct, terms, albedo, lights, exposure=1.5)
    assert errors["reference_bounces"] == 3
    for name, light in lights.items():
        rel, psnr = _plain_errors(direct, terms, albedo, light, 1.5)
        np.testing.assert_allclose(errors[name]["rel_mae"], rel, rtol=1e-9)
        np.testing.assert_allclose(errors[name]["psnr"], psnr, rtol=1e-6)
    # Keeping more terms leaves less out here (terms of one sign on average): the error falls.
    assert errors["a"]["rel_mae"][0] > errors["a"]["rel_mae"][2]


def test_choose_bounces_takes_the_smallest_n_under_every_light():
    errors = {"reference_bounces": 4, "x": {"psnr": [20.0, 45.0, 55.0, 70.0]}, "y": {"psnr": [30.0, 52.0, 49.0, 60.0]}}
    assert choose_bounces(errors, 50.0) == 3  # N = 1 fails x, N = 2 fails y
    assert choose_bounces(errors, 40.0) == 1
    assert choose_bounces(errors, 80.0) == 3  # none meets it: the largest measured


def _precompute(mesh: "trimesh.Trimesh", tmp_path: Path):
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.precompute import PrecomputeSettings, load_precompute, run_precompute

    path = tmp_path / "mesh.obj"
    mesh.export(path)
    geometry = load_geometry(str(path))
    settings = PrecomputeSettings(samples=1500, validation=600, rays=32, segments=1)
    run_precompute(geometry, tmp_path / "pre", settings, threads=1, progress=False, log=lambda line: None)
    data = load_precompute(tmp_path / "pre")
    return path, geometry, data["samples"], data["validation"]


def _open_box() -> "trimesh.Trimesh":
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    keep = box.face_normals[:, 1] < 0.5  # no lid
    return trimesh.Trimesh(box.vertices, box.faces[keep], process=False)


@pytest.mark.parametrize("shape", ["sphere", "open_box"])
def test_auto_keeps_no_bounce_on_a_convex_object_and_some_in_a_box(shape, tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=3) if shape == "sphere" else _open_box()
    _, geometry, train, valid = _precompute(mesh, tmp_path)
    albedos = {name: [0.7, 0.7, 0.7] for name in geometry.object_names}
    lines = []
    count, record = auto_bounces(geometry, tmp_path / "cache", train, valid, albedos, _lights(), rays=16, chunk_size=512, key="k",
                                 threads=1, progress=False, log=lines.append)  # fmt: skip
    assert record["reference_bounces"] == AUTO_MAX_BOUNCES and set(record["psnr"]) == set(BUNDLED_ENVMAPS)
    assert any(line.startswith("bounces auto:") for line in lines)
    if shape == "sphere":  # rays leaving a convex surface hit nothing: no term, nothing truncated
        assert count == 0
        assert all(p[0] == PSNR_CAP for p in record["psnr"].values())
    else:  # the walls light each other: stopping at N = 0 misses light a render shows
        assert 1 <= count < AUTO_MAX_BOUNCES - 1  # and the terms fall off: a count that meets the threshold
        assert min(p[0] for p in record["psnr"].values()) < AUTO_PSNR
        assert all(p[count] >= AUTO_PSNR for p in record["psnr"].values())
        assert all(r[0] > r[count] for r in record["rel_mae"].values())


def test_spec_and_command_line_take_auto():
    from prt.train.build import BuildSpec, spec_from_dict
    from prt.train.train_cli import build_parser

    spec = spec_from_dict({**BuildSpec(geometry="x").to_dict(), "bounces": "auto"})
    assert spec.bounces == "auto"
    with pytest.raises(SpecError, match="bounces: expected int"):
        spec_from_dict({**BuildSpec(geometry="x").to_dict(), "bounces": "often"})
    parser = build_parser()
    assert parser.parse_args(["m.obj", "-o", "o", "--bounces", "auto"]).bounces == "auto"
    assert parser.parse_args(["m.obj", "-o", "o", "--bounces", "3"]).bounces == 3
    with pytest.raises(SystemExit):
        parser.parse_args(["m.obj", "-o", "o", "--bounces", "often"])


def test_build_with_auto_records_the_choice(tmp_path):
    from prt.runtime.manifest import load_manifest
    from prt.train.build import BuildSpec, run_build, spec_from_dict

    path = tmp_path / "box.obj"
    _open_box().export(path)
    data = {**BuildSpec(geometry=str(path)).to_dict(), "samples": 1500, "validation": 600, "rays": 32, "segments": 1, "steps": 20,
            "bounces": "auto", "bounce_rays": 16, "fixed": {"hidden": 8, "layers": 1}, "analytic": False}  # fmt: skip
    report = run_build(spec_from_dict(data), tmp_path / "out", threads=1, progress=False, log=lambda line: None)
    chosen = report["interreflection"]["bounces"]
    assert chosen >= 1 and report["spec"]["bounces"] == chosen
    manifest = load_manifest(tmp_path / "out" / "scene.json")  # the schema takes the record
    assert manifest.interreflection.bounces == chosen
    auto = manifest.interreflection.auto
    assert auto["threshold_psnr"] == AUTO_PSNR and min(auto["psnr"][k][chosen] for k in auto["psnr"]) >= AUTO_PSNR
    assert json.loads((tmp_path / "out" / "build.json").read_text())["interreflection"]["auto"] == auto
