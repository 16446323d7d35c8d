"""Build presets: ``prt-train MESH --quality draft|standard|high``.

A preset bundles the settings that trade build time for fidelity: samples and rays of the
ground truth, the k-d split's leaf budget, the fit's steps and batch, the bounce rays, and the
capacity the default sizing rule may grow to (its ladder of network sizes) with the margin it
aims for over per-vertex PRT (:mod:`prt.train.networks.rightsize`, rule ``"vertex"``), and the
absolute floor of the build's held-out PSNR (``floor_db``, diffuse under the scene's lighting) with
the wall-clock seconds of the whole build (``build_budget``) it may spend reaching it: a build under
its floor keeps splitting segments and growing networks until it is over it or the time is spent
(:mod:`prt.train.refine`).  The leaf budget grows with the scene (:func:`leaf_budget`).

A margin over per-vertex PRT alone is no bar where per-vertex PRT fails too (a building, a CAD
assembly: issue 43), hence the floor.  The floors sit under what the presets reach on single
objects (standard: bunny 42.3, Spot 41.8, a 15k-vertex scan 39.0 dB; draft 36.1, 36.2, 33.0 dB;
``docs/benchmarks/presets*.json``), so those builds never refine and keep their bytes.

A spec's own fields and ``prt-train``'s flags win over the preset: :func:`resolve` fills only
the fields a spec leaves out, and the build records the preset, the values it resolved to and
which of them differ (``build.json``'s ``spec`` and ``preset``).  ``standard`` is the default
(measured cost and fidelity of each: ``docs/benchmarks/presets.md``); a spec built with
:class:`prt.train.build.BuildSpec` directly keeps the dataclass's defaults, the paper's setting.
"""

from __future__ import annotations

import copy
import math

__all__ = ["QUALITIES", "DEFAULT_QUALITY", "PRESETS", "RULE_FIELDS", "FLOOR_FIELDS", "LEAF_CAP", "SAMPLES_PER_LEAF",
           "LEAVES_PER_OBJECT", "leaf_budget", "resolve", "differences", "describe"]

QUALITIES = ("draft", "standard", "high")
DEFAULT_QUALITY = "standard"

# The ladder sizes a preset lets the default rule grow to, smallest first (prt.train.networks.fit.DEFAULT_LADDER's
# sizes; a draft stops at k = 64, l = 3: its larger fits would take most of its time).
_SMALL_LADDER = [
    {"hidden": 16, "layers": 2, "pos_freqs": 4},
    {"hidden": 32, "layers": 2, "pos_freqs": 5},
    {"hidden": 32, "layers": 3, "pos_freqs": 6},
    {"hidden": 48, "layers": 3, "pos_freqs": 6},
    {"hidden": 64, "layers": 3, "pos_freqs": 6},
]

# The high preset's ladder: the default one and a size past k = 128, l = 4 (0.5 MB of fp32 weights with
# bounces), room a dense mesh's per-vertex PRT leaves; it fits at about 0.2 s a step (batch 8192) on two cores.
_HIGH_LADDER = [*_SMALL_LADDER, {"hidden": 64, "layers": 4, "pos_freqs": 6}, {"hidden": 128, "layers": 4, "pos_freqs": 6},
                {"hidden": 192, "layers": 4, "pos_freqs": 6}]

PRESETS: dict[str, dict] = {
    # A first look at a new mesh in minutes: a tenth of the samples, half the rays, short fits, networks up to k64-l3.
    "draft": {"samples": 100_000, "rays": 256, "segments": 8, "steps": 400, "batch": 4096, "bounce_rays": 16,
              "vertex_margin": 1.0, "ladder": _SMALL_LADDER, "floor_db": 30.0, "build_budget": 300.0},
    # The default.  The paper's rays, half its samples: the fits of the old default (1M samples, 2000 steps of
    # 8192, --match 64x4) took 1,633 of a 15k-vertex scan's 1,881 s (issue 35).  Many small steps: a fit on two
    # cores is bound by its count of Adam steps more than by the samples each sees; 4000 steps of 256 take
    # about the time of the former 1000 of 4096 and fitted the Duplex house's segments 2-6 dB better held out
    # (studies/fit_batch.py, docs/benchmarks/fit_batch_duplex.md).
    "standard": {"samples": 500_000, "rays": 512, "segments": 8, "steps": 4000, "batch": 256, "bounce_rays": 32,
                 "vertex_margin": 1.0, "ladder": None, "floor_db": 35.0, "build_budget": 1200.0},
    # The paper's samples and steps, twice its rays and leaves, twice the bounce rays, a 2 dB margin.
    "high": {"samples": 1_000_000, "rays": 1024, "segments": 16, "steps": 2000, "batch": 8192, "bounce_rays": 64,
             "vertex_margin": 2.0, "ladder": _HIGH_LADDER, "floor_db": 38.0, "build_budget": 3600.0},
}
"""Quality name -> the flat build-spec fields it sets (:meth:`prt.train.build.BuildSpec.to_dict`)."""

# Fields that name a sizing rule: a spec that names one keeps it, and the preset's own rule
# (``vertex_margin``, with its ``ladder``) is left out.
RULE_FIELDS = ("fixed", "ladder", "match", "target", "target_db", "vertex_margin")

# The preset's floor and its time: left out, as the rule, where a spec names a rule of its own, and
# where it asks for fewer samples than its preset (a quick look, not the preset's promise); a spec
# naming them (``--floor``, ``--build-budget``) keeps them.
FLOOR_FIELDS = ("floor_db", "build_budget")

# The leaf budget (``segments``) of a preset build grows with the scene (:func:`leaf_budget`).
SAMPLES_PER_LEAF = 62_500  # the presets' own ratio: standard 500k / 8 leaves, high 1M / 16
LEAVES_PER_OBJECT = 2  # a multi-object scene: room for one cut in every object beyond its own leaf
LEAF_CAP = {"draft": 32, "standard": 64, "high": 128}  # and the most segments refinement may make


def leaf_budget(quality: str | None, leaves: int, objects: int, samples: int) -> int:
    """The k-d split's leaf budget of a preset build: ``min(cap, max(preset leaves, 2 x objects,
    ceil(samples / 62,500)))`` (:data:`LEAVES_PER_OBJECT`, :data:`SAMPLES_PER_LEAF`, the cap
    :data:`LEAF_CAP`); a single object at the preset's samples keeps the preset's leaves.  The
    split still gives every object a leaf of its own (:func:`prt.train.networks.segments.segment_samples`)."""
    cap = LEAF_CAP.get(quality or DEFAULT_QUALITY, LEAF_CAP[DEFAULT_QUALITY])
    wanted = max(int(leaves), LEAVES_PER_OBJECT * int(objects), math.ceil(int(samples) / SAMPLES_PER_LEAF))
    return max(int(leaves), min(cap, wanted))


def resolve(data: dict) -> dict:
    """``data`` (flat spec fields as given: a spec file's, the flags') with its preset's values
    filled in where it leaves a field out, and ``quality`` set.

    The quality is ``data["quality"]`` or :data:`DEFAULT_QUALITY`; an unknown one is left for
    the spec check to refuse.  A spec naming a sizing rule (:data:`RULE_FIELDS`, or an encoding
    other than "freq") keeps it: the preset's ``vertex_margin`` and ``ladder`` are not applied.
    """
    quality = data.get("quality") or DEFAULT_QUALITY
    preset = copy.deepcopy(PRESETS.get(quality, {}))
    names_rule = any(data.get(k) is not None for k in RULE_FIELDS if k != "vertex_margin") or data.get("encoding", "freq") != "freq"
    if names_rule:  # (a margin of its own keeps the preset's ladder)
        preset.pop("vertex_margin", None)
        preset.pop("ladder", None)
    given = data.get("samples")  # (a value of the wrong type is left for the spec check to refuse)
    fewer = isinstance(given, (int, float)) and not isinstance(given, bool) and given < preset.get("samples", 0)
    if names_rule or fewer:  # the floor's own fields given keep it
        for key in FLOOR_FIELDS:
            preset.pop(key, None)
    if data.get("epochs") is not None and data.get("steps") is None:
        preset.pop("steps", None)  # epochs alone: the old epoch-based run (prt.train.networks.fit.FitSettings)
    # absent fields only: a field given as null keeps its meaning (an old build.json's "steps": null, DEFAULT_STEPS)
    filled = {k: v for k, v in preset.items() if v is not None and k not in data}
    return {**data, **filled, "quality": quality}


def differences(spec: dict) -> dict:
    """The fields of a resolved spec (flat, :meth:`prt.train.build.BuildSpec.to_dict`) whose values
    differ from its preset's: what flags or the spec file set by hand.  ``{field: [preset, value]}``."""
    preset = PRESETS.get(spec.get("quality") or DEFAULT_QUALITY, {})
    # a floor left out (with a rule of the spec's own, or fewer samples) follows from those fields: not listed again
    return {k: [v, spec[k]] for k, v in preset.items() if k in spec and spec[k] != v and not (k in FLOOR_FIELDS and spec[k] is None)}


def describe(quality: str) -> str:
    """One line of a preset's values, for ``--help``."""
    p = PRESETS[quality]
    top = (p["ladder"] or [{"hidden": 128, "layers": 4}])[-1]  # None: the default ladder (prt.train.networks.fit.DEFAULT_LADDER)
    return (f"{p['samples'] // 1000:,}k samples x {p['rays']} rays, {p['segments']} leaves, {p['steps']} steps of {p['batch']}, "
            f"{p['bounce_rays']} bounce rays, networks up to k{top['hidden']}-l{top['layers']} sized to beat vertex PRT by "
            f"{p['vertex_margin']:g} dB, refined while under {p['floor_db']:g} dB for up to {p['build_budget'] / 60:g} min")
