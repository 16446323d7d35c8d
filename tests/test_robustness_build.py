"""Hostile and careless input to the build side (issue 16): one test per class of defect.

The corpus (tests/hostile/cases_build.py) covers single bad inputs through the commands; these
tests cover what needs more than one command or a look inside the files.
"""

import errno
import json
import os
import stat

import numpy as np
import pytest

from prt.runtime.errors import GeometryError, OutputError, PRTError, SpecError
from prt.runtime.files import atomic_write_json
from prt.train import precompute_cli
from prt.train.outdir import MARKER, check_output_folder
from prt.train.transport.precompute import DamagedPrecompute, load_precompute

TET = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
TINY = ["--samples", "256", "--validation", "64", "--rays", "16", "--segments", "2", "--threads", "1", "--no-progress"]


@pytest.fixture
def tet(tmp_path):
    path = tmp_path / "tet.obj"
    path.write_text(TET)
    return path


def _precompute(tet, out, *extra):
    return precompute_cli.main([str(tet), "-o", str(out), *TINY, *extra])


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# -- class 1: data loss -------------------------------------------------------------------------


def test_a_folder_not_ours_is_refused_and_force_overrides(tet, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "segments.json").write_text("my own file\n")
    assert _precompute(tet, out) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a prt build folder" in err and "--force" in err
    assert _files(out) == {"segments.json": b"my own file\n"}

    assert _precompute(tet, out, "--force") == 0
    assert json.loads((out / MARKER).read_text()) == {"format": "prt-build", "version": 1, "kind": "precompute"}
    assert _precompute(tet, out) == 0  # now ours: a rerun resumes without --force
    assert "up to date" in capsys.readouterr().out


def test_a_build_made_before_the_marker_is_recognised(tet, tmp_path):
    out = tmp_path / "old"
    assert _precompute(tet, out) == 0
    (out / MARKER).unlink()  # as a build made before the marker existed
    check_output_folder(out, "precompute")
    scene = tmp_path / "scene"
    (scene / "precompute").mkdir(parents=True)
    for name, data in _files(out).items():
        (scene / "precompute" / name).parent.mkdir(parents=True, exist_ok=True)
        (scene / "precompute" / name).write_bytes(data)
    check_output_folder(scene, "scene")  # precompute/precompute.json: an old scene build
    with pytest.raises(OutputError, match="holds a precompute build"):
        check_output_folder(out, "scene")


def test_the_marker_is_written_before_any_other_file(tet, tmp_path, monkeypatch, capsys):
    def broken(*args, **kwargs):
        raise GeometryError("stop here")

    monkeypatch.setattr("prt.train.transport.precompute.make_tracer", broken)
    out = tmp_path / "out"
    assert _precompute(tet, out) == 2
    assert sorted(p.name for p in out.iterdir()) == [MARKER]


# -- class 5: tracebacks (the rest are in the corpus) ------------------------------------------


def test_foreign_or_corrupt_cache_files_are_cache_misses(tet, tmp_path):
    out = tmp_path / "out"
    assert _precompute(tet, out) == 0
    first = _files(out)
    (out / "precompute.json").write_text('["not", "a summary"]')
    for chunk in sorted(out.glob("cache/*/chunk_*.npy"))[:2]:
        chunk.write_bytes(b"\x93NUMPY garbage")  # a damaged chunk is computed again
    assert _precompute(tet, out) == 0
    assert {k: v for k, v in _files(out).items() if k != "precompute.json"} == {k: v for k, v in first.items() if k != "precompute.json"}


def test_a_truncated_precompute_file_is_one_line(tet, tmp_path):
    out = tmp_path / "out"
    assert _precompute(tet, out) == 0
    data = (out / "samples.npz").read_bytes()
    (out / "samples.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(DamagedPrecompute, match=r"samples\.npz: damaged") as info:
        load_precompute(out)
    assert "\n" not in str(info.value)


def test_cached_training_records_that_are_not_ours_are_ignored(tmp_path):
    from prt.train.build import _FitCache, _loadable, _read_record
    from prt.train.networks.fit import FitSettings
    from prt.train.networks.network import Architecture

    for text in ("{", "[]", '{"kind": "magic"}', "\xff"):
        (tmp_path / "seg000.json").write_text(text, encoding="latin-1")
        assert _read_record(tmp_path / "seg000.json") is None
    (tmp_path / "seg000.npz").write_bytes(b"PK\x03\x04 truncated")
    assert not _loadable(tmp_path / "seg000.npz")
    fits = _FitCache(tmp_path / "fits", "key", 0, FitSettings())
    arch = Architecture(hidden=8, layers=1)
    meta, weights = fits._paths(arch)
    meta.parent.mkdir()
    np.savez(weights, w=np.zeros(3))
    meta.write_text('{"arch": 1}')  # foreign: no val_mae
    assert fits.get(arch) is None


def test_a_truncated_geometry_npz_is_one_line(tmp_path):
    from prt.runtime.gbuffer import load_mesh

    path = tmp_path / "geometry.npz"
    np.savez(path, vertices=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 2]], dtype=np.uint32))
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(GeometryError, match=r"geometry\.npz: cannot read mesh"):
        load_mesh(path)


def test_a_full_disk_is_one_line_and_leaves_no_temporary_file(tet, tmp_path, monkeypatch, capsys):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("prt.runtime.files.os.fsync", full)
    with pytest.raises(OutputError, match=r"a\.json: cannot write \(No space left on device\)"):
        atomic_write_json(tmp_path / "a.json", {"x": 1})
    assert list(tmp_path.iterdir()) == [tet]

    out = tmp_path / "deep" / "out"
    assert _precompute(tet, out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0]
    assert not (tmp_path / "deep").exists()  # the marker could not be written: nothing is left


def test_negative_threads_in_the_library(tmp_path):
    from prt.train.build import BuildSpec, run_build

    with pytest.raises(SpecError, match="threads"):
        run_build(BuildSpec(geometry="x.obj"), tmp_path / "out", threads=-2)
    assert not (tmp_path / "out").exists()


# -- class 7: file modes follow the umask -------------------------------------------------------


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077])
def test_outputs_honour_the_umask(tet, tmp_path, umask):
    old = os.umask(umask)
    try:
        out = tmp_path / "out"
        assert _precompute(tet, out) == 0
    finally:
        os.umask(old)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert files and {stat.S_IMODE(p.stat().st_mode) for p in files} == {0o666 & ~umask}


# -- class 8: the whole spec is checked before any work ------------------------------------------


def test_the_whole_spec_is_checked_before_any_work(tet, tmp_path, monkeypatch, capsys):
    from prt.train import train_cli

    def no_work(*args, **kwargs):
        raise AssertionError("work started on a bad spec")

    monkeypatch.setattr("prt.train.build.load_geometry", no_work)
    monkeypatch.setattr("prt.train.build.run_precompute", no_work)
    bad = {
        "material": {"type": "diffuse", "albedo": [1, 1]},
        "camera": {"eye": [0, 0, 0], "target": [0, 0, 0]},
        "ladder": [],
        "match": {"hidden": 0},
    }
    for field, value in bad.items():
        spec = tmp_path / "spec.json"
        spec.write_text(json.dumps({"geometry": str(tet), field: value}))
        assert train_cli.main([str(spec), "-o", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"spec.json: {field}" in err
    assert not (tmp_path / "out").exists()


# -- class 10: no empty output folders ------------------------------------------------------------


def test_a_failed_command_creates_no_folder(tmp_path, capsys):
    from prt.train import train_cli

    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nf 1 1 1\n")
    out = tmp_path / "a" / "b" / "out"
    assert train_cli.main([str(bad), "-o", str(out)]) == 2
    assert precompute_cli.main([str(bad), "-o", str(out)]) == 2
    assert not (tmp_path / "a").exists()


# -- class 12: minor ---------------------------------------------------------------------------------


def test_faces_with_nan_vertices_are_counted(tmp_path):
    from prt.train.inputs.geometry import load_geometry

    path = tmp_path / "nan.obj"
    path.write_text(TET + "v nan 0 0\nf 5 1 2\nf 5 2 3\n")
    geometry = load_geometry(path)
    assert geometry.dropped_nonfinite == 2 and len(geometry.mesh.faces) == 4
    assert "2 triangles with NaN/Inf vertices dropped" in geometry.summary()


@pytest.mark.parametrize("scale", [1e300, 1e-300, 1e307])
def test_huge_and_tiny_coordinates_load_like_unit_ones(tmp_path, scale):
    from prt.train.inputs.geometry import load_geometry

    unit = tmp_path / "unit.obj"
    unit.write_text(TET)
    scaled = tmp_path / "scaled.obj"
    scaled.write_text("".join(f"v {' '.join(repr(float(x) * scale) for x in line.split()[1:])}\n" if line.startswith("v ") else line + "\n"
                              for line in TET.splitlines()))
    a, b = load_geometry(unit), load_geometry(scaled)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    assert np.allclose(b.to_source[:3, :3], a.to_source[:3, :3] * scale, rtol=1e-12)


def test_a_non_boolean_two_sided_is_rejected(tmp_path):
    from prt.runtime.gbuffer import load_mesh

    path = tmp_path / "geometry.npz"
    np.savez(path, vertices=np.eye(3, dtype=np.float32), faces=np.array([[0, 1, 2]], dtype=np.uint32), two_sided=np.array([2.5]))
    with pytest.raises(GeometryError, match="two_sided must be booleans"):
        load_mesh(path)


def test_errors_are_project_errors():
    assert issubclass(OutputError, PRTError) and issubclass(OutputError, OSError)
