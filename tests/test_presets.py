"""prt-train --quality: presets fill what a spec leaves out, flags and spec fields win, the spec records it; --help by stage."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from prt.runtime.errors import SpecError
from prt.train.build import BuildSpec, DEFAULT_TARGET, spec_from_dict
from prt.train.presets import DEFAULT_QUALITY, PRESETS, QUALITIES, differences, resolve
from prt.train.train_cli import _spec_from_args, build_parser


def _cli_spec(*argv):
    return _spec_from_args(build_parser().parse_args([*map(str, argv)]))


@pytest.mark.parametrize("quality", QUALITIES)
def test_a_preset_sets_its_values_and_the_spec_records_them(quality):
    spec = spec_from_dict({"geometry": "x.obj", "quality": quality})
    flat, preset = spec.to_dict(), PRESETS[quality]
    assert flat["quality"] == quality
    for key in ("samples", "rays", "segments", "steps", "batch", "bounce_rays", "vertex_margin", "ladder"):
        assert flat[key] == preset[key], key
    assert differences(flat) == {}
    # build.json's spec reads back as the same build
    assert spec_from_dict(json.loads(json.dumps(flat))).to_dict() == flat


def test_the_default_quality_is_standard_and_it_sizes_against_vertex_prt():
    spec = spec_from_dict({"geometry": "x.obj"})
    assert spec.quality == DEFAULT_QUALITY == "standard"
    assert spec.vertex_margin == PRESETS["standard"]["vertex_margin"] and spec.match is None
    assert spec.target == DEFAULT_TARGET  # the analytic cap
    assert spec.precompute.samples == PRESETS["standard"]["samples"] and spec.steps == PRESETS["standard"]["steps"]


def test_flags_override_the_preset_and_the_rest_of_it_stays(tmp_path):
    spec = _cli_spec("m.obj", "-o", tmp_path / "o", "--quality", "draft", "--samples", 5000, "--steps", 77)
    draft = PRESETS["draft"]
    assert (spec.precompute.samples, spec.steps) == (5000, 77)
    assert (spec.precompute.rays, spec.precompute.segments, spec.batch, spec.bounce_rays) == (draft["rays"], draft["segments"], draft["batch"],
                                                                                             draft["bounce_rays"])  # fmt: skip
    assert differences(spec.to_dict()) == {"samples": [draft["samples"], 5000], "steps": [draft["steps"], 77]}


def test_a_spec_file_names_its_preset_its_fields_win_and_flags_win_over_both(tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"geometry": "m.obj", "quality": "high", "rays": 300}))
    spec = _cli_spec(path, "-o", tmp_path / "o")
    assert (spec.quality, spec.precompute.rays, spec.precompute.samples) == ("high", 300, PRESETS["high"]["samples"])
    spec = _cli_spec(path, "-o", tmp_path / "o", "--quality", "draft", "--rays", 40)
    assert (spec.quality, spec.precompute.rays, spec.precompute.samples) == ("draft", 40, PRESETS["draft"]["samples"])


@pytest.mark.parametrize("flags, field, value", [
    (["--hidden", "16", "--layers", "2"], "fixed", {"hidden": 16, "layers": 2}),
    (["--match", "32x3"], "match", {"hidden": 32, "layers": 3}),
    (["--target-db", "38"], "target_db", 38.0),
    (["--target", "0.004"], "target", 0.004),
])
def test_a_named_rule_replaces_the_presets_rule_and_its_ladder(tmp_path, flags, field, value):
    spec = _cli_spec("m.obj", "-o", tmp_path / "o", "--quality", "draft", *flags)
    assert getattr(spec, field) == value
    assert spec.vertex_margin is None and spec.ladder is None
    assert spec.precompute.samples == PRESETS["draft"]["samples"]  # the rest of the preset stays


def test_a_margin_of_ones_own_keeps_the_presets_ladder(tmp_path):
    spec = _cli_spec("m.obj", "-o", tmp_path / "o", "--quality", "draft", "--vertex-margin", "3")
    assert spec.vertex_margin == 3.0 and spec.ladder == PRESETS["draft"]["ladder"]


@pytest.mark.parametrize("data, message", [
    ({"quality": "best"}, "quality: expected one of draft, standard, high"),
    ({"vertex_margin": 1.0, "match": {"hidden": 64, "layers": 4}}, "vertex_margin: cannot be combined with match"),
    ({"vertex_margin": float("nan")}, "vertex_margin"),
    ({"vertex_margin": 1.0, "target_db": 40}, "vertex_margin: cannot be combined with target_db"),
])
def test_bad_presets_and_margins_are_one_line_errors(data, message):
    with pytest.raises(SpecError, match=message):
        spec_from_dict({"geometry": "x.obj", **data})


def test_epochs_alone_keep_the_epoch_based_run(tmp_path):
    spec = _cli_spec("m.obj", "-o", tmp_path / "o", "--epochs", "3")
    assert spec.epochs == 3 and spec.steps is None  # not the preset's steps: "at least 3 passes" would be a longer run
    assert _cli_spec("m.obj", "-o", tmp_path / "o", "--epochs", "3", "--steps", "50").steps == 50


def test_resolve_leaves_given_fields_alone():
    data = resolve({"geometry": "x", "quality": "draft", "samples": 10, "steps": None})
    assert data["samples"] == 10 and data["ladder"] == PRESETS["draft"]["ladder"] and data["rays"] == PRESETS["draft"]["rays"]
    assert data["steps"] is None  # given as null: the library's default, as in an old build.json


def test_help_is_grouped_by_stage_with_the_preset_first():
    parser = build_parser()
    titles = [g.title for g in parser._action_groups if g._group_actions]
    assert titles[-5:] == ["preset", "input", "precompute", "networks", "export"]
    group = {a.dest: g.title for g in parser._action_groups for a in g._group_actions}
    assert group["quality"] == "preset" and group["samples"] == "precompute" and group["steps"] == "networks"
    assert group["glsl_layout"] == "export" and group["name"] == "input" and group["bounces"] == "precompute"
    text = subprocess.run([sys.executable, "-m", "prt.train.train_cli", "--help"], capture_output=True, text=True).stdout
    assert text.index("--quality") < text.index("--samples") < text.index("--steps") < text.index("--glsl-layout")
    assert "(default: None)" not in text


def test_an_unknown_quality_on_the_command_line_is_a_usage_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "prt.train.train_cli", "m.obj", "-o", str(tmp_path / "o"), "--quality", "best"],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 2 and "invalid choice: 'best'" in proc.stderr and "Traceback" not in proc.stderr
