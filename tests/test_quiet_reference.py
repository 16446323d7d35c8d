"""The quiet reference's plan (bench/quiet_reference.py): which rays to raise, within caps and a time budget."""

from __future__ import annotations

import math

import pytest

from prt.bench.quiet_reference import quiet_plan
from prt.bench.report import _floor_reason


def _db(mse: float) -> float:
    return -10 * math.log10(mse)


def test_a_reference_already_quiet_keeps_its_rays():
    plan = quiet_plan({"diffuse": 50.0}, None, {"diffuse": 40.0}, 1024, 64, rays_max=4096, hit_rays_max=1024, seconds_direct=10.0,
                      seconds_bounce=0.0, views=30, budget=3600.0)  # fmt: skip
    assert (plan["rays"], plan["met"], plan["reason"], plan["needs"]) == (1024, True, None, None)


def test_direct_noise_raises_the_direct_rays_by_the_doublings_the_margin_needs():
    # 4 dB short of best + 6: one doubling (variance halves: +3.01 dB) is not enough, two are.
    plan = quiet_plan({"diffuse": 42.0}, None, {"diffuse": 40.0}, 1024, 64, rays_max=8192, hit_rays_max=1024, seconds_direct=1.0,
                      seconds_bounce=0.0, views=10, budget=None)  # fmt: skip
    assert (plan["rays"], plan["hit_rays"], plan["met"]) == (4096, 64, True)
    assert plan["predicted_noise_psnr"]["diffuse"] == pytest.approx(42.0 + 10 * math.log10(4), abs=0.01)


def test_bounce_noise_raises_the_bounce_rays_and_the_cheaper_mix_wins():
    # Total noise 40 dB, nearly all of it the bounce part's: doubling the direct rays cannot help.
    total = 10 ** -4.0
    bounce = 0.95 * total
    plan = quiet_plan({"diffuse": 40.0}, {"diffuse": _db(bounce)}, {"diffuse": 36.0}, 512, 64, rays_max=4096, hit_rays_max=1024,
                      seconds_direct=1.0, seconds_bounce=4.0, views=10, budget=None)  # fmt: skip
    assert plan["met"] and plan["rays"] == 512 and plan["hit_rays"] == 128  # 42 dB needed: half the bounce variance does it
    predicted = (total - bounce) + bounce / 2
    assert plan["predicted_noise_psnr"]["diffuse"] == pytest.approx(_db(predicted), abs=0.01)
    # Both parts alike and the bounce part expensive: the direct rays go up first.
    even = quiet_plan({"diffuse": 40.0}, {"diffuse": _db(total / 2)}, {"diffuse": 35.5}, 512, 64, rays_max=4096, hit_rays_max=1024,
                      seconds_direct=1.0, seconds_bounce=100.0, views=10, budget=None)  # fmt: skip
    assert even["met"] and (even["rays"], even["hit_rays"]) == (2048, 64)  # 4x the direct rays: cheaper than 2x both


def test_caps_and_budget_stop_it_and_say_what_it_would_need():
    capped = quiet_plan({"glossy": 40.0}, None, {"glossy": 40.0}, 1024, 64, rays_max=2048, hit_rays_max=64, seconds_direct=1.0,
                        seconds_bounce=0.0, views=10, budget=None)  # fmt: skip
    assert (capped["rays"], capped["met"], capped["reason"]) == (2048, False, "caps")
    assert capped["needs"]["rays"] == 4096 and capped["needs"]["seconds"] == pytest.approx(40.0)
    poor = quiet_plan({"glossy": 40.0}, None, {"glossy": 40.0}, 1024, 64, rays_max=1 << 20, hit_rays_max=64, seconds_direct=30.0,
                      seconds_bounce=0.0, views=30, budget=1900.0)  # fmt: skip
    # 4x the rays would take 30 x 120 s = 3600 s > 1900 s: it stops at 2x (1800 s), short of the margin.
    assert (poor["rays"], poor["met"], poor["reason"], poor["seconds"]) == (2048, False, "budget", 1800.0)
    assert poor["needs"] == {"rays": 4096, "hit_rays": 64, "seconds": 3600.0}
    text = _floor_reason({"reason": "budget", "needs": poor["needs"]})
    assert "--ref-budget" in text and "4096 rays" in text and "3600 s" in text
    assert "--ref-rays-max" in _floor_reason({"reason": "caps", "needs": capped["needs"]})
    assert _floor_reason({"reason": None}) == ""


def test_unknown_times_do_not_block_and_materials_all_count():
    plan = quiet_plan({"diffuse": 50.0, "glossy": 41.0}, None, {"diffuse": 40.0, "glossy": 40.0}, 256, 64, rays_max=4096, hit_rays_max=64,
                      seconds_direct=None, seconds_bounce=None, views=30, budget=1.0)  # fmt: skip
    assert plan["met"] and plan["rays"] == 1024 and plan["seconds"] is None  # the glossy shortfall (5 dB) decides


def test_reference_mitsuba_without_mitsuba_is_one_line_and_exit_2(monkeypatch, capsys, tmp_path):
    import importlib.util

    from prt.bench import cli

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mitsuba" else real(name, *a))
    assert cli.main([str(tmp_path / "scene.json"), "--reference", "mitsuba"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'prt-runtime[mitsuba]'" in err[0]


@pytest.mark.parametrize("flag", [["--mitsuba-spp", "1"], ["--mitsuba-views", "0"], ["--ref-budget", "-1"], ["--ref-hit-rays-max", "0"],
                                  ["--mitsuba-variant", "cuda_ad_rgb"]])  # fmt: skip
def test_bad_reference_options_are_usage_errors(flag, capsys):
    from prt.bench import cli

    with pytest.raises(SystemExit) as exc:
        cli.parse_args(["scene.json", *flag])
    assert exc.value.code == 2
