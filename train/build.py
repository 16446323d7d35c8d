"""The whole build: precompute -> train (right-sized per segment) -> export (ONNX, GLSL, manifest).

Each stage is cached in the output folder and resumes after an interruption:

    OUTDIR/precompute/          samples, ground-truth transfer, segments (prt.train.transport.precompute)
    OUTDIR/train/segNNN.json    per-segment fit: chosen size, errors, sizes tried (+ .npz weights)
    OUTDIR/refine/segNNN.json   a segment refitted under the floor (prt.train.refine; + .npz weights)
    OUTDIR/segments/, geometry.npz, scene.json   the scene folder, written by prt.export.scene
    OUTDIR/build.json           the report: per-segment table, memory, timings
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import time
from contextlib import closing, contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..export.scene import TrainedSegment, export_scene
from ..runtime.camera import DEFAULT_CAMERA, Camera
from ..runtime.envmap import load_envmap_sh
from ..runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path
from ..runtime.errors import SpecError
from ..runtime.files import atomic_save_npz, atomic_write_json
from ..runtime.manifest import validate_manifest_field
from .networks.fit import DEFAULT_LADDER, DEFAULT_LOSS, DEFAULT_STEPS, FIT_THREADS, LOSSES, FitSettings
from .inputs.geometry import load_geometry
from .inputs.materials import mesh_materials, textured_geometry
from .inputs.mixed import load_scene_geometry, parse_objects, resolve_objects
from .executor import LocalExecutor
from .fit_cache import FIT_FORMAT, _FitCache, _FitMemo, _StoredModel  # noqa: F401  (FIT_FORMAT, _FitCache: re-exported)
from .networks.grid_encoding import DEFAULT_GRID, GridArchitecture, parse_grid
from .networks.network import Architecture
from .outdir import check_output_folder, mark_output_folder
from .presets import PRESETS, QUALITIES, leaf_budget
from .refine import RefineJob, refine_build, scene_psnr
from .presets import differences as preset_differences
from .progress import BOUNCE_RAY, EXPORT_SEGMENT, RAY, BuildProgress, step_cost
from .transport.vertex_estimate import estimate_vertex_prt
from .presets import resolve as resolve_preset
from .transport.interreflection import BOUNCE_RAYS, RAY_RULE, TRACE_RULE, bounce_stage
from .transport.smoothing import SMOOTH_NEIGHBOURS, SMOOTH_RULE, smooth_indirect
from .transport.transfer import EmbreeTracer
from .transport.bounce_depth import auto_bounces
from .networks.rightsize import HEAD_MODES, RESIDUAL_MODES, SCENE_LIGHT, SegmentJob, candidates, scene_sizing, segment_task
from .transport.precompute import SPEC_LIMITS, DamagedPrecompute, PrecomputeSettings, SpecLimits, check_settings, load_precompute, run_precompute

__all__ = ["BuildSpec", "SpecLimits", "SPEC_LIMITS", "load_spec", "spec_from_dict", "run_build", "ENV_LIGHTS"]

ENV_LIGHTS = tuple(BUNDLED_ENVMAPS)  # the shaded-error lightings, in the bundled order
TRAIN_FORMAT = 2  # 2: a fixed-size build keeps a segment analytic only where as accurate as its network
VERTEX_RULE_VERSION = "vertex-v2"  # v2: the estimate's indirect part by the bounce estimator on the vertices  # the "vertex" rule's part of a segment's cache key: raise it when the estimate changes

# The precompute settings a build spec sets, by their flat names (chunk_size is not a spec field).
PRECOMPUTE_FIELDS = tuple(f.name for f in dataclasses.fields(PrecomputeSettings) if f.name != "chunk_size")


@dataclass
class BuildSpec:
    """Everything a build does.  Defaults reproduce the paper's setting where it has one.

    A spec file (JSON) and :meth:`to_dict` are flat: the fields of :attr:`precompute`
    (:data:`PRECOMPUTE_FIELDS`) sit beside the others.
    """

    geometry: str = ""
    name: str = ""
    # the preset the spec was resolved with (prt.train.presets: its values fill the fields a spec leaves out)
    quality: str | None = None
    precompute: PrecomputeSettings = field(default_factory=PrecomputeSettings)
    # training (prt.train.networks.fit.FitSettings.plan): ``steps`` Adam steps per network whatever its sample
    # count; ``epochs`` alone (old specs, ``--epochs``): the old epoch-based run; both: steps, with
    # at least ``epochs`` passes over the data; ``time_budget``: seconds per network fit
    steps: int | None = None  # None: DEFAULT_STEPS, unless ``epochs`` alone asks for the old epoch-based run
    epochs: int | None = None
    time_budget: float | None = None
    batch: int = 8192
    lr: float = 1e-2
    patience: int = 10
    bf16: bool | None = False  # bf16 autocast: about 2x faster on AVX512-BF16, about 9 % higher error
    loss: str = DEFAULT_LOSS  # fitting loss (prt.train.networks.fit.LOSSES): "auto" (per segment by visibility), "l2", "l1", "relative"
    # frequency networks learn the direct transfer's residual from the unshadowed transfer of the
    # normal (prt.train.networks.network): "auto" per segment by its mean visibility (prt.train.networks.rightsize), "on", "off"
    residual: str = "auto"
    # frequency networks' output head (prt.train.networks.network.HEADS): "linear", "log-dc", or "auto":
    # log-DC where a segment's mean visibility is under 0.8 (prt.train.networks.rightsize.HEAD_MODES).
    # Not the default: built so, the Duplex and AS1 copies came out worse (docs/guides/build.md)
    head: str = "linear"
    # validation coefficient MAE a right-sized network must reach (None: DEFAULT_TARGET; a spec
    # that names no sizing rule gets its preset's vertex_margin, prt.train.presets)
    target: float | None = None
    # right-size to a shaded target instead (prt.train.networks.rightsize): the cheapest size whose held-out
    # shaded, tone-mapped PSNR (dB, under the scene lighting, rightsize.SCENE_LIGHT) is at least this
    target_db: float | None = None
    # right-size by the error reached against per-vertex PRT (prt.train.networks.rightsize, rule "vertex"): per
    # segment the cheapest size whose held-out shaded PSNR is this many dB above the vertex PRT estimate's,
    # within the segment's share of vertex PRT's bytes; the default rule of mesh builds
    vertex_margin: float | None = None
    ladder: list[dict] | None = None  # [{hidden, layers, pos_freqs, normal_freqs}], small to large
    fixed: dict | None = None  # force one size for every network segment
    match: dict | None = None  # right-size to this size's accuracy ({hidden, layers, ...}) instead of ``target``
    match_tolerance: float = 0.05  # with ``match``: validation MAE may exceed the reference's by this share
    analytic: bool = True  # let unshadowed segments skip the network
    # the networks' encoding of position: "freq" (the paper's frequency-encoded MLP) or "grid" (a
    # multiresolution feature grid feeding a small MLP, prt.train.networks.grid_encoding; ``grid`` spells its
    # levels, e.g. "L6-F2-T12-N4-32", None: DEFAULT_GRID); ``fixed``/``ladder`` then size its MLP;
    # "auto": right-size per segment over both (the frequency ladder and the grid ladder)
    encoding: str = "freq"
    grid: str | None = None
    # interreflection (prt.train.transport.interreflection): N diffuse bounces (0: direct transfer only, the
    # paper's); N > 0 fits "direct+rgb" networks (direct + indirect R, G, B transfer)
    bounces: int | Literal["auto"] = "auto"  # "auto": the smallest N whose truncation error is small (prt.train.transport.bounce_depth); 0: the paper's direct transfer
    bounce_rays: int = BOUNCE_RAYS
    # export
    glsl_layout: str = "auto"
    material: dict = field(default_factory=lambda: {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]})
    camera: dict = field(default_factory=lambda: {k: list(v) if isinstance(v, tuple) else v for k, v in DEFAULT_CAMERA.items()})
    # the absolute floor of the held-out PSNR (dB, diffuse under the scene's lighting) and the build's wall-clock seconds
    # to reach it: while under it, segments are split and networks grown (prt.train.refine); None: no floor
    floor_db: float | None = None
    build_budget: float | None = None
    objects: list[dict] | None = None  # a mixed scene (prt.train.inputs.mixed): meshes, SDFs, neural SDFs; ``geometry`` is then its label

    @property
    def bands(self) -> int:
        return self.precompute.bands

    @property
    def seed(self) -> int:
        return self.precompute.seed

    @property
    def layout(self) -> str:
        """The networks' output layout (:data:`prt.train.networks.network.LAYOUTS`)."""
        return "direct+rgb" if self.bounces else "direct"

    def to_dict(self) -> dict:
        """The spec as flat JSON fields (what a spec file holds and ``build.json`` records)."""
        out = {"geometry": self.geometry, "name": self.name}
        out |= {k: getattr(self.precompute, k) for k in PRECOMPUTE_FIELDS}
        out |= {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in out and f.name != "precompute"}
        return copy.deepcopy(out)

    def fit_settings(self) -> FitSettings:
        return FitSettings(epochs=self.epochs, batch=self.batch, lr=self.lr, patience=self.patience, seed=self.seed, bf16=self.bf16,
                           steps=self.steps, max_seconds=self.time_budget, loss=self.loss)  # fmt: skip

    def architectures(self) -> list[Architecture] | list[GridArchitecture]:
        """The sizes to try, smallest first (one when ``fixed``)."""
        if self.encoding == "grid":
            return _grid_architectures(self)
        if self.encoding == "auto":  # both ladders, cheapest first
            return candidates([dataclasses.replace(a, bands=self.bands, layout=self.layout) for a in DEFAULT_LADDER], _grid_architectures(self))
        if self.fixed is not None:
            return [_architecture(self.fixed, self.bands, "fixed", self.layout)]
        if self.ladder is not None:
            return [_architecture(a, self.bands, f"ladder[{i}]", self.layout) for i, a in enumerate(self.ladder)]
        return [dataclasses.replace(a, bands=self.bands, layout=self.layout) for a in DEFAULT_LADDER]

    def vertex_rule(self) -> bool:
        """True where the spec sizes by the error reached against per-vertex PRT (rule "vertex")."""
        return self.vertex_margin is not None

    def reference_architecture(self) -> Architecture | None:
        """The size whose accuracy right-sizing matches (``match``), or None (absolute ``target``)."""
        return None if self.match is None else _architecture(self.match, self.bands, "match", self.layout)


def _shown(key: str) -> str:
    """A field name as an error message shows it: quoted if it would break the line or vanish."""
    return key if key.isprintable() and key.strip() == key and key else repr(key)


def _architecture(d: dict, bands: int, where: str, layout: str = "direct") -> Architecture:
    allowed = {"hidden", "layers", "pos_freqs", "normal_freqs"}
    if not isinstance(d, dict):
        raise SpecError(f"{where}: expected an object with {sorted(allowed)}")
    extra = set(d) - allowed
    if extra:
        raise SpecError(f"{where}.{_shown(sorted(extra)[0])}: unknown field (known: {', '.join(sorted(allowed))})")
    for key, value in d.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < (0 if key.endswith("freqs") else 1):
            raise SpecError(f"{where}.{key}: expected a {'non-negative' if key.endswith('freqs') else 'positive'} integer, got {value!r}")
        most = getattr(SPEC_LIMITS, "freqs" if key.endswith("freqs") else key)
        if value > most:
            raise SpecError(f"{where}.{key}: at most {most}, got {value}")
    base = Architecture()
    return Architecture(
        hidden=d.get("hidden", base.hidden),
        layers=d.get("layers", base.layers),
        pos_freqs=d.get("pos_freqs", base.pos_freqs),
        normal_freqs=d.get("normal_freqs", base.normal_freqs),
        bands=bands,
        layout=layout,
    )


# The MLP sizes a grid build right-sizes over by default (the study's, docs/benchmarks/grid_encoding.md).
GRID_LADDER = ({"hidden": 16, "layers": 1}, {"hidden": 32, "layers": 2}, {"hidden": 64, "layers": 2}, {"hidden": 64, "layers": 3})


def _grid_architectures(spec: BuildSpec) -> list[GridArchitecture]:
    """``encoding: "grid"``: the grid ``spec.grid`` with the MLP sizes of ``fixed``, ``ladder`` or GRID_LADDER."""
    try:
        grid = parse_grid(DEFAULT_GRID if spec.grid is None else spec.grid)
    except ValueError as exc:
        raise SpecError(f"grid: {exc}") from None
    if spec.fixed is not None:
        sizes = [("fixed", spec.fixed)]
    elif spec.ladder is not None:
        sizes = [(f"ladder[{i}]", a) for i, a in enumerate(spec.ladder)]
    else:
        sizes = [(f"grid ladder[{i}]", a) for i, a in enumerate(GRID_LADDER)]
    out = []
    for where, d in sizes:
        if isinstance(d, dict) and "pos_freqs" in d:
            raise SpecError(f"{where}.pos_freqs: not used by the grid encoding (the grid encodes position); leave it out")
        a = _architecture(d, spec.bands, where, spec.layout)
        if a.hidden % 4:
            raise SpecError(f"{where}.hidden: the grid's GLSL reads its MLP in vec4s: expected a multiple of 4, got {a.hidden}")
        out.append(GridArchitecture(**grid, hidden=a.hidden, layers=a.layers, normal_freqs=d.get("normal_freqs", 0), bands=spec.bands,
                                    layout=spec.layout))  # fmt: skip
    return out


# The sizing rule of scenes the default rule ("vertex", prt.train.presets) cannot size, having no
# vertices (SDF and mixed scenes): per segment the cheapest ladder size as accurate as k = 64, l = 4
# (within match_tolerance), the measured Pareto front's choice (docs/benchmarks/many_networks.md).
# DEFAULT_TARGET: the MAE target of --target / ladder builds, and the cap below which a segment
# stays analytic under match.
DEFAULT_MATCH = {"hidden": 64, "layers": 4}
DEFAULT_TARGET = 0.0025


# Flat spec field -> its annotation (the precompute fields come from PrecomputeSettings).
_TYPES = {
    **{f.name: f.type for f in dataclasses.fields(BuildSpec) if f.name in ("geometry", "name")},
    **{f.name: f.type for f in dataclasses.fields(PrecomputeSettings) if f.name in PRECOMPUTE_FIELDS},
    **{f.name: f.type for f in dataclasses.fields(BuildSpec) if f.name not in ("geometry", "name", "precompute")},
}


def load_spec(path) -> BuildSpec:
    """Read a build spec (JSON).  Errors name the file and the field."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
        data = json.loads(text)
    except FileNotFoundError:
        raise SpecError(f"{path}: no such file") from None
    except OSError as exc:
        raise SpecError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise SpecError(f"{path}: not UTF-8 text (byte {exc.start}); a build spec is JSON in UTF-8") from None
    except json.JSONDecodeError as exc:
        raise SpecError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    except RecursionError:
        raise SpecError(f"{path}: not valid JSON (nested too deeply)") from None
    except ValueError as exc:  # an integer of more than 4300 digits
        raise SpecError(f"{path}: not usable JSON ({' '.join(str(exc).split())[:120]})") from None
    if not isinstance(data, dict):
        raise SpecError(f"{path}: expected a JSON object at the top level")
    try:
        spec = spec_from_dict(data)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from None
    geometry = Path(spec.geometry)
    if not geometry.is_absolute() and (path.parent / geometry).exists():
        spec.geometry = str(path.parent / geometry)
    if spec.objects:
        spec.objects = resolve_objects(spec.objects, path)
    return spec


def spec_from_dict(data: dict) -> BuildSpec:
    """A checked spec from flat fields (as :meth:`BuildSpec.to_dict` gives them).  Errors name the field.

    Everything is checked here, before any work: types, ranges, finiteness, limits
    (:data:`SPEC_LIMITS`, :func:`prt.train.transport.precompute.sample_limit`), the ladder, material and camera.
    """
    if not isinstance(data, dict):
        raise SpecError(f"expected an object of fields, got {type(data).__name__}")
    if data.get("quality") is not None and data["quality"] not in QUALITIES:
        raise SpecError(f"quality: expected one of {', '.join(QUALITIES)}, got {data['quality']!r}")
    data = resolve_preset(data)
    known = set(_TYPES)
    for key, value in data.items():
        if key not in known:
            raise SpecError(f"{_shown(key)}: unknown field (known: {', '.join(sorted(known))})")
        kind = _TYPES[key]
        ok = {
            "str": isinstance(value, str),
            "str | None": value is None or isinstance(value, str),
            "int": isinstance(value, int) and not isinstance(value, bool),
            "int | None": value is None or (isinstance(value, int) and not isinstance(value, bool)),
            "int | Literal['auto']": value == "auto" or (isinstance(value, int) and not isinstance(value, bool)),
            "float | None": value is None or (isinstance(value, (int, float)) and not isinstance(value, bool)),
            "float": isinstance(value, (int, float)) and not isinstance(value, bool),
            "bool": isinstance(value, bool),
            "bool | None": value is None or isinstance(value, bool),
            "list[dict] | None": value is None or isinstance(value, list),
            "dict | None": value is None or isinstance(value, dict),
            "dict": isinstance(value, dict),
        }[kind]
        if not ok:
            raise SpecError(f"{key}: expected {kind}, got {type(value).__name__} {value!r}")
    if data.get("objects") is not None:  # a mixed scene: objects checked, geometry is only a label
        data = {"geometry": "mixed", **data, "objects": [o.to_dict() for o in parse_objects(data["objects"])]}
    if "geometry" not in data:
        raise SpecError("geometry: missing (a mesh file or a built-in SDF scene name)")
    if not data["geometry"].strip() or "\0" in data["geometry"]:
        raise SpecError(f"geometry: expected a mesh file or a built-in SDF scene name, got {data['geometry']!r}")
    precompute = PrecomputeSettings(**{k: v for k, v in data.items() if k in PRECOMPUTE_FIELDS})
    spec = BuildSpec(**{k: v for k, v in data.items() if k not in PRECOMPUTE_FIELDS}, precompute=precompute)
    flat = spec.to_dict()
    check_settings(spec.precompute)
    for key in ("steps", "epochs", "batch", "patience", "bounce_rays"):
        if flat[key] is not None and not 1 <= flat[key] <= getattr(SPEC_LIMITS, key):
            raise SpecError(f"{key}: expected 1 .. {getattr(SPEC_LIMITS, key)}, got {flat[key]}")
    if spec.bounces != "auto" and (isinstance(spec.bounces, str) or not 0 <= spec.bounces <= SPEC_LIMITS.bounces):
        raise SpecError(f"bounces: expected 0 .. {SPEC_LIMITS.bounces} (0: direct light only) or 'auto', got {spec.bounces!r}")
    if spec.target is None:
        spec.target = flat["target"] = DEFAULT_TARGET
    for key, positive in (("lr", True), ("target", False), ("time_budget", True), ("build_budget", True), ("floor_db", True)):
        value = flat[key]
        if value is None and key in ("time_budget", "build_budget", "floor_db"):
            continue
        if not math.isfinite(value) or value < 0 or (positive and value == 0):
            raise SpecError(f"{key}: expected a finite {'positive' if positive else 'non-negative'} number, got {value!r}")
    if spec.glsl_layout not in ("auto", "const", "texture"):
        raise SpecError(f"glsl_layout: expected 'auto', 'const' or 'texture', got {spec.glsl_layout!r}")
    if spec.loss not in LOSSES:
        raise SpecError(f"loss: expected one of {', '.join(map(repr, LOSSES))}, got {spec.loss!r}")
    if spec.residual not in RESIDUAL_MODES:
        raise SpecError(f"residual: expected one of {', '.join(map(repr, RESIDUAL_MODES))}, got {spec.residual!r}")
    if spec.head not in HEAD_MODES:
        raise SpecError(f"head: expected one of {', '.join(map(repr, HEAD_MODES))}, got {spec.head!r}")
    if spec.head == "log-dc" and spec.residual == "on":
        raise SpecError("head: 'log-dc' and residual: 'on' exclude each other (a residual network's head is linear)")
    if spec.residual == "on" and spec.bands > 4:
        raise SpecError(f"residual: 'on' needs at most 4 SH bands (the unshadowed transfer is then a quadratic of the normal), not {spec.bands}")
    if spec.encoding not in ("freq", "grid", "auto"):
        raise SpecError(f"encoding: expected 'freq' (the paper's frequency-encoded MLP), 'grid' (a multiresolution feature grid) or 'auto' "
                        f"(right-sized over both), got {spec.encoding!r}")  # fmt: skip
    if spec.encoding == "auto":
        for key in ("fixed", "ladder"):
            if getattr(spec, key) is not None:
                raise SpecError(f"{key}: not with encoding 'auto' (it right-sizes over the frequency ladder and the grid ladder; "
                                f"choose encoding 'freq' or 'grid' to set sizes)")  # fmt: skip
    if spec.floor_db is not None and spec.floor_db > 100:
        raise SpecError(f"floor_db: expected a PSNR in dB, 0 < dB <= 100, got {spec.floor_db!r}")
    if spec.vertex_margin is not None:
        if not (isinstance(spec.vertex_margin, (int, float)) and math.isfinite(spec.vertex_margin) and -20 <= spec.vertex_margin <= 20):
            raise SpecError(f"vertex_margin: expected dB above the vertex PRT estimate, -20 .. 20, got {spec.vertex_margin!r}")
        for key in ("fixed", "match", "target_db"):
            if getattr(spec, key) is not None:
                raise SpecError(f"vertex_margin: cannot be combined with {key} (one right-sizing rule per build)")
        if spec.encoding != "freq":
            raise SpecError(f"vertex_margin: sizes frequency networks only, not encoding {spec.encoding!r}")
    if spec.target_db is not None:
        if isinstance(spec.target_db, bool) or not isinstance(spec.target_db, (int, float)) or not (0 < spec.target_db <= 100):
            raise SpecError(f"target_db: expected a PSNR in dB, 0 < dB <= 100, got {spec.target_db!r}")
        for key in ("fixed", "match"):
            if getattr(spec, key) is not None:
                raise SpecError(f"target_db: cannot be combined with {key} (one right-sizing rule per build)")
    if spec.encoding == "freq":
        if spec.grid is not None:
            raise SpecError(f"grid: only with encoding 'grid' or 'auto' (got encoding {spec.encoding!r})")
    else:
        for key, value, why in (("glsl_layout", spec.glsl_layout == "const", "a grid's tables are always a texture"),
                                ("time_budget", spec.time_budget is not None, "grids train by steps only"),
                                ("bf16", bool(spec.bf16) or spec.bf16 is None, "grids train in fp32")):  # fmt: skip
            if value:
                raise SpecError(f"{key}: {getattr(spec, key)!r} is not supported with encoding {spec.encoding!r} ({why})")
    if spec.ladder is not None and not spec.ladder:
        raise SpecError("ladder: empty (list at least one size, or leave it out for the default ladder)")
    spec.architectures()  # validates ladder / fixed
    if spec.match is not None:
        if spec.fixed is not None:
            raise SpecError("match: cannot be combined with fixed (a fixed size has nothing to right-size)")
        spec.reference_architecture()  # validates match
    if not 0.0 <= spec.match_tolerance <= 1.0:
        raise SpecError(f"match_tolerance: expected a share in [0, 1], got {spec.match_tolerance}")
    _check_material_and_camera(spec.material, spec.camera)
    return spec


def _check_material_and_camera(material: dict, camera: dict) -> None:
    """What export would refuse, refused now: the manifest schema, float32 range, a camera that sees."""
    for key, value in (("material", material), ("camera", camera)):
        try:
            validate_manifest_field(key, value, "spec")
        except SpecError as exc:
            raise SpecError(str(exc).removeprefix("spec: ")) from None
        for where, number in _numbers(value, key):
            if not abs(number) <= _FLOAT32_MAX:  # NaN fails too
                raise SpecError(f"{where}: expected a finite number (in float32), got {number!r}")
    view = {**DEFAULT_CAMERA, **camera}
    try:
        Camera(eye=view["eye"], target=view["target"], up=view["up"], fov_y=view["fov"])
    except ValueError as exc:
        raise SpecError(f"camera: {str(exc).removeprefix('Camera: ')}") from None


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _numbers(value, where: str):
    """(field path, number) of every number inside a JSON value."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield where, value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{where}[{i}]")


def _env_lights(bands: int) -> dict[str, np.ndarray]:
    return {name: load_envmap_sh(bundled_envmap_path(name), bands) for name in ENV_LIGHTS}


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_build(spec: BuildSpec, out_dir, *, threads: int | None = None, progress=True, log=print, force: bool = False,
              executor=None, device: str = "cpu", started: float | None = None) -> dict:  # fmt: skip
    """Run (or resume) a build; returns the report written to ``build.json``.

    ``started``: the ``time.perf_counter()`` the build's time counts from (``prt-train`` passes its
    process's start, so that the preset's ``build_budget`` bounds what the user waits for, imports
    and argument checks included); default: now.

    ``progress``: True draws the build's one progress line on a terminal (:class:`prt.train.progress.BuildProgress`;
    nothing when stderr is not one), False none, or a display of the caller's.

    ``executor`` runs the transfer chunks and the segment fits (:mod:`prt.train.executor`;
    default: ``threads`` threads here).  A cluster gives the same bytes and the same caches.

    ``device`` (``"cpu"`` or ``"cuda"``, :func:`prt.train.networks.fit.resolve_device`) is where the
    frequency networks train; it keys no cache and enters no file, so a CPU build's bytes do not
    depend on it and a fit cached on either device serves the other.

    ``out_dir`` must be new, empty or a scene build of ours unless ``force``
    (:func:`prt.train.outdir.check_output_folder`); it is created once the geometry has loaded.
    """
    display = progress if isinstance(progress, BuildProgress) else BuildProgress(enabled=bool(progress))
    if log is print:
        log = display.log  # log lines above the progress line
    try:
        return _run_build(spec, out_dir, threads=threads, display=display, log=log, force=force, executor=executor, device=device,
                          started=started)  # fmt: skip
    finally:
        if display is not progress:
            display.close()


def _run_build(spec: BuildSpec, out_dir, *, threads, display: BuildProgress, log, force: bool, executor, device: str = "cpu",
               started: float | None = None) -> dict:  # fmt: skip
    t_start = time.perf_counter() if started is None else float(started)
    out = Path(out_dir)
    progress = display
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise SpecError(f"threads: expected a positive integer, got {threads!r}")
    check_output_folder(out, "scene", force=force)
    if threads:
        torch.set_num_threads(threads)
    executor = executor if executor is not None else LocalExecutor(threads)
    geometry = load_scene_geometry(spec) if spec.objects else load_geometry(spec.geometry)
    name = spec.name or Path(spec.geometry).stem
    log(geometry.summary())
    # The mesh's own per-object materials (MTL, glTF); transfer does not depend on them.
    materials = mesh_materials(spec.geometry, geometry.object_names, spec.material, log) if geometry.sdf is None else []
    materials = geometry.mixed.materials if geometry.mixed is not None else materials
    materials, albedo_uv = textured_geometry(spec.geometry, geometry, materials, log)
    if spec.bounces == "auto" and geometry.kind != "mesh":  # the default: direct transfer where bounces are not built
        log(f"bounces: auto -> 0 (interreflection is built for triangle meshes; this is {'an SDF' if geometry.kind == 'sdf' else 'a mixed'} scene)")
        spec = dataclasses.replace(spec, bounces=0)
    if spec.vertex_rule() and geometry.kind != "mesh":  # no vertices to compare with: the measured front's rule
        log(f"sizing: the vertex PRT rule needs a triangle mesh; this is {'an SDF' if geometry.kind == 'sdf' else 'a mixed'} scene: "
            f"--match {DEFAULT_MATCH['hidden']}x{DEFAULT_MATCH['layers']} instead")  # fmt: skip
        spec = dataclasses.replace(spec, vertex_margin=None, match=dict(DEFAULT_MATCH))
    if spec.bounces and geometry.kind != "mesh":
        raise SpecError(f"bounces: interreflection needs a triangle mesh; {spec.geometry!r} is {'an SDF' if geometry.kind == 'sdf' else 'a mixed'} scene (use --bounces 0)")
    mark_output_folder(out, "scene")
    differs = preset_differences(spec.to_dict())  # what was set by hand (before the leaf budget follows the scene)
    spec, leaves = _scene_leaves(spec, geometry, log)

    # -- stage 1: precompute
    t0 = time.perf_counter()
    pre = spec.precompute
    display.expect("precompute", (pre.samples + pre.validation_count()) * pre.rays * RAY)
    if spec.bounces != 0 and geometry.kind == "mesh":
        display.expect("bounces", (pre.samples + pre.validation_count()) * spec.bounce_rays * BOUNCE_RAY)
    if spec.vertex_rule():
        display.expect("vertices", len(geometry.mesh.vertices) * pre.rays * RAY)
    display.expect("export", spec.precompute.segments * EXPORT_SEGMENT)
    per_segment = _expected_fit_work(spec, spec.architectures(), spec.fit_settings(), pre.samples // max(pre.segments, 1))
    display.plan_fits({s: per_segment for s in range(pre.segments)}, spec.batch)  # revised once the segments are known
    display.begin("precompute")
    pre_summary = run_precompute(geometry, out / "precompute", spec.precompute, threads=threads, progress=progress, log=log, force=force,
                                     executor=executor)
    try:
        data = load_precompute(out / "precompute")
    except DamagedPrecompute as exc:  # a cache miss: recompute (finished transfer chunks are reused)
        log(f"precompute: {exc}; recomputing")
        (out / "precompute" / "precompute.json").unlink(missing_ok=True)
        pre_summary = run_precompute(geometry, out / "precompute", spec.precompute, threads=threads, progress=progress, log=log, force=force,
                                     executor=executor)
        data = load_precompute(out / "precompute")
    precompute_s = time.perf_counter() - t0
    display.finish("precompute")
    samples, valid, members = data["samples"], data["validation"], data["members"]
    # -- stage 1b: bounces (interreflection), before fitting; the fits' cache keys follow its settings
    t0 = time.perf_counter()
    data_key, interreflection, auto = pre_summary["key"], None, None
    bounce_key = _hash(pre_summary["key"], spec.bounce_rays, spec.seed, spec.precompute.chunk_size, "v2")  # v2: the tangent-plane nearest-sample rule
    if spec.bounces == "auto":  # rays traced once (the cache bounce_stage then reads); N measured on the validation samples
        auto_n, auto = auto_bounces(geometry, out / "precompute" / "cache", samples, valid, _object_albedos(geometry, materials, spec.material),
                                    _env_lights(spec.bands), rays=spec.bounce_rays, seed=spec.seed, chunk_size=spec.precompute.chunk_size,
                                    key=bounce_key, executor=executor, threads=threads, progress=progress, log=log)  # fmt: skip
        spec = dataclasses.replace(spec, bounces=auto_n)
    if spec.bounces:
        albedos = _object_albedos(geometry, materials, spec.material)
        # RAY_RULE: rays entering the surface carry nothing, hits take only samples on their side of walls;
        # TRACE_RULE: hits far from a clear sample get their direct transfer traced; SMOOTH_RULE: the
        # training targets' indirect part averaged over neighbours
        data_key = _hash(pre_summary["key"], spec.bounces, spec.bounce_rays, albedos, "v3", RAY_RULE, TRACE_RULE, SMOOTH_RULE)
        log(f"bounces: {spec.bounces} diffuse bounce(s), {spec.bounce_rays} rays per sample ({len(samples['points']):,} + "
            f"{len(valid['points']):,} samples)")  # fmt: skip
        face_albedo = np.asarray([albedos[n] for n in geometry.object_names], dtype=np.float64)[geometry.object_ids]
        indirect, valid_indirect = bounce_stage(
            geometry.mesh, out / "precompute" / "cache", samples, valid, face_albedo, spec.bounces, rays=spec.bounce_rays, seed=spec.seed,
            chunk_size=spec.precompute.chunk_size, key=bounce_key,
            executor=executor, threads=threads, progress=progress, log=log,
        )  # fmt: skip
        t1 = time.perf_counter()
        # The training samples' indirect part averaged with their nearest on the same side (the gather's
        # noise out); the held-out samples keep theirs, so held-out errors stay against independent targets.
        indirect = smooth_indirect(samples["points"], samples["normals"], indirect, tracer=EmbreeTracer(geometry.mesh))
        log(f"bounces: training targets' indirect part averaged over each sample's {SMOOTH_NEIGHBOURS} nearest on its side of walls "
            f"({time.perf_counter() - t1:.1f} s)")  # fmt: skip
        for part, extra in ((samples, indirect), (valid, valid_indirect)):  # [direct, indirect R, G, B]
            part["transfer"] = np.concatenate([part["transfer"], extra.transpose(0, 2, 1).reshape(len(extra), -1)], axis=1)
        interreflection = {"bounces": spec.bounces, "bounce_rays": spec.bounce_rays, "layout": spec.layout, "albedos": albedos,
                           **({"auto": auto} if auto else {})}  # fmt: skip
    bounce_s = time.perf_counter() - t0
    display.finish("bounces")
    seg_json = data["segments"]
    lights = _env_lights(spec.bands)

    # -- stage 1c: per-vertex PRT estimated on the held-out samples (the "vertex" sizing rule's bar)
    t0 = time.perf_counter()
    vertex = None
    if spec.vertex_rule():
        display.begin("vertices", "vertex transfer")
        vertex = estimate_vertex_prt(geometry, out / "precompute" / "cache" / "vertices", rays=spec.precompute.rays, bands=spec.bands,
                                     seed=spec.seed, chunk_size=spec.precompute.chunk_size, bounces=spec.bounces,
                                     face_albedo=face_albedo if spec.bounces else None, executor=executor, threads=threads,
                                     progress=display, log=log)  # fmt: skip
        display.finish("vertices")
    vertex_s = time.perf_counter() - t0

    # -- stage 2: train; segments are independent tasks (threads here or a cluster), each cached
    t0 = time.perf_counter()
    fit_settings = dataclasses.replace(spec.fit_settings(), device=device)
    archs = spec.architectures()
    records, todo = {}, []
    for seg in seg_json["segments"]:
        s = seg["id"]
        key = _hash(data_key, s, fit_settings.cache_key(), [a.as_dict() for a in archs], spec.target, spec.analytic, TRAIN_FORMAT,
                    *([spec.residual] if spec.residual != "off" else []),
                    *([("head", spec.head)] if spec.head != "linear" else []),
                    *([spec.match, spec.match_tolerance] if spec.match is not None else []),
                    *([spec.target_db, spec.material] if spec.target_db is not None else []),
                    *([spec.vertex_margin, spec.material, VERTEX_RULE_VERSION] if spec.vertex_rule() else []))  # fmt: skip
        record_path = out / "train" / f"seg{s:03d}.json"
        weights_path = out / "train" / f"seg{s:03d}.npz"
        record = _read_record(record_path)
        if record is not None:
            if record.get("key") == key and (record["kind"] == "analytic" or _loadable(weights_path)):
                log(f"segment {s}: cached ({record['kind']}{', ' + record['arch_label'] if record['kind'] == 'network' else ''})")
                records[s] = record
                continue
        todo.append((seg, key))
    fits_folder = out / "precompute" / "fits"
    job = SegmentJob(spec, samples, valid, members, archs, fit_settings, lights, display if executor.local else False,
                     log if executor.local else None, vertex)  # fmt: skip
    items = []
    for seg, key in todo:  # a cluster gets the fits cached before with its task; its new fits come back
        fits = _FitCache(fits_folder, data_key, seg["id"], fit_settings)
        items.append((seg, key, fits if executor.local else fits.memo([*archs, *filter(None, [spec.reference_architecture()])])))
    expected = {seg["id"]: _expected_fit_work(spec, archs, fit_settings, len(members[seg["id"]])) for seg, _ in todo}
    display.plan_fits(expected, fit_settings.batch)
    display.begin("fits", f"{len(todo)} segment(s) to fit" if todo else "cached")
    # Fits run FIT_THREADS torch threads each, as many at once as the executor has cores (here: threads
    # of this process, each fit seeding under a lock, prt.train.networks.fit.seeded); a fit's bytes
    # depend on its thread count only, not on how many run beside it or where.
    torch_threads = torch.get_num_threads()
    try:
        with _fit_threads(executor.local), closing(executor.map(segment_task, job, items, task_threads=FIT_THREADS)) as finished:
            for (seg, _, _), (record, new_fits, lines) in finished:
                s = seg["id"]
                for line in lines:
                    log(line)
                fits = _FitCache(fits_folder, data_key, s, fit_settings)
                for result in new_fits:
                    fits.put(result)
                if record["kind"] == "network":
                    atomic_save_npz(out / "train" / f"seg{s:03d}.npz", **record.pop("arrays"))
                atomic_write_json(out / "train" / f"seg{s:03d}.json", record)
                records[s] = record
                if not executor.local:  # its steps ran elsewhere: the segment's planned work, done now
                    display.add("fits", expected[s])
                display.segment_done(s)
    finally:
        display.finish("fits")
    segments = [records[seg["id"]] for seg in seg_json["segments"]]
    train_s = time.perf_counter() - t0

    # -- stage 2b: refinement while under the floor (prt.train.refine), within the build's time
    t0, refinement = time.perf_counter(), None
    if spec.floor_db is not None and geometry.kind == "mesh":
        fit_cache = lambda pre_key, s, settings: _FitCache(fits_folder, pre_key, s, settings)  # noqa: E731
        job = RefineJob(spec, out, seg_json, samples, valid, members, archs, fit_settings, lights, vertex, data_key, fit_cache,
                        list(geometry.object_names), t_start, log, threads=torch_threads)  # fmt: skip
        with _fit_threads():  # its refits run torch_threads at a time
            segments, seg_json, refinement = refine_build(job, segments)
    refine_s = time.perf_counter() - t0
    held_out = {"light": SCENE_LIGHT, "psnr_db": scene_psnr(segments), "floor_db": spec.floor_db}
    exported = [_with_scene_psnr(r, held_out) for r in segments]

    # -- stage 3: export
    t0 = time.perf_counter()
    display.expect("export", len(segments) * EXPORT_SEGMENT)
    display.begin("export", "ONNX, GLSL, scene.json")
    manifest = export_scene(
        out,
        name=name,
        geometry=geometry,
        segmentation={
            "roots": {int(k): v for k, v in seg_json["roots"].items()},
            "nodes": seg_json["nodes"],
            "leaf_segment": np.asarray(seg_json["leaf_segment"], dtype=np.int64),
        },
        segments=[_trained_segment(record, out) for record in exported],
        sh_bands=spec.bands,
        lighting_sh=lights[SCENE_LIGHT],
        material=spec.material,
        camera=spec.camera,
        glsl_layout=spec.glsl_layout,
        materials=materials,
        albedo_uv=albedo_uv,
        interreflection=interreflection,
        envmap=bundled_envmap_path(SCENE_LIGHT),  # the map lighting_sh came from: the new build's background
    )
    memory = manifest.memory
    display.add("export", len(segments) * EXPORT_SEGMENT)
    display.finish("export")
    export_s = time.perf_counter() - t0

    report = {
        "name": name,
        "source": geometry.source,
        "spec": spec.to_dict(),
        "segments": [{k: v for k, v in r.items() if k not in ("key", "history")} for r in segments],
        "memory": {
            "weight_bytes": memory.weight_bytes,
            "vertex_storage_bytes": memory.vertex_storage_bytes,
            "vertices": int(len(geometry.mesh.vertices)),
        },
        **({"interreflection": interreflection or {"bounces": 0, "auto": auto}} if auto else {}),
        "preset": {"quality": spec.quality, "differs": differs},
        "leaf_budget": leaves,
        "held_out": held_out,
        **({"refinement": refinement} if refinement is not None else {}),
        **({"sizing": {**scene_sizing(segments, vertex.weight_bytes, spec.vertex_margin), **held_out}} if vertex is not None else {}),
        "timings": {
            "precompute_s": precompute_s,
            **({"bounce_s": bounce_s} if spec.bounces or auto else {}),
            **({"vertex_s": vertex_s} if vertex is not None else {}),
            "train_s": train_s,
            **({"refine_s": refine_s} if refinement is not None else {}),
            "export_s": export_s,
            "total_s": time.perf_counter() - t_start,
            "transfer_rays_per_s": pre_summary["timings"]["rays_per_s"],
        },
    }
    atomic_write_json(out / "build.json", report)
    return report


@contextmanager
def _fit_threads(here: bool = True):
    """Torch at FIT_THREADS threads in this process while fits run here (``here``), as before after."""
    before = torch.get_num_threads()
    if here:
        torch.set_num_threads(FIT_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _expected_fit_work(spec: BuildSpec, archs, fit_settings, samples: int) -> float:
    """The progress display's estimate of one segment's fits (weighted work, :mod:`prt.train.progress`):
    the fits its sizing rule usually takes (a bisection: about log2 of the sizes + 1, a match: its
    reference and one or two smaller sizes, plus the residual probe's) at the middle size's cost."""
    if not archs:
        return 0.0
    fits = 1.0 if spec.fixed is not None else (math.floor(math.log2(len(archs))) + 1.5 if spec.match is None else 3.0)
    batch, steps, _, _ = fit_settings.plan(max(int(samples), 1))
    middle = spec.reference_architecture() or archs[(len(archs) - 1) // 2]
    return fits * steps * step_cost(middle.flops_per_fragment(), batch)


def _scene_leaves(spec: BuildSpec, geometry, log) -> tuple[BuildSpec, dict]:
    """A preset build's leaf budget, grown with the scene (:func:`prt.train.presets.leaf_budget`); a
    ``segments`` other than the preset's is the spec's own and stays.  (spec, build.json's ``leaf_budget``)"""
    pre, objects = spec.precompute, len(geometry.object_names)
    preset = PRESETS.get(spec.quality or "", {})
    if preset.get("segments") != pre.segments:
        return spec, {"rule": "given", "leaves": pre.segments, "objects": objects}
    leaves = leaf_budget(spec.quality, pre.segments, objects, pre.samples)
    if leaves != pre.segments:
        log(f"segments: leaf budget {leaves} for {objects} objects and {pre.samples:,} samples (preset {pre.segments})")
        spec = dataclasses.replace(spec, precompute=dataclasses.replace(pre, segments=leaves))
    return spec, {"rule": "scene", "leaves": leaves, "preset": preset["segments"], "objects": objects, "samples": pre.samples}


def _with_scene_psnr(record: dict, held_out: dict) -> dict:
    """A segment's record for export: its manifest ``sizing`` also gives the scene's pooled held-out PSNR and the floor."""
    sizing = record.get("sizing")
    if sizing is None:
        return record
    extra = {"scene_psnr_db": held_out["psnr_db"], **({"floor_db": held_out["floor_db"]} if held_out["floor_db"] is not None else {})}
    return {**record, "sizing": {**sizing, **extra, **({"refined": record["refined"]} if "refined" in record else {})}}


def _object_albedos(geometry, materials, default: dict) -> dict[str, list[float]]:
    """The diffuse albedo (``Kd``) of every object, as the bounces use it: the mesh's own per-object
    material, else the scene-wide one.  A glossy surface bounces its diffuse part only; an albedo
    texture is not sampled at the bounce (its object's ``Kd`` stands for it)."""
    found = {m.object: [float(a) for a in m.material.albedo] for m in materials}
    base = [float(a) for a in default.get("albedo", [0.7, 0.7, 0.7])]
    return {name: found.get(name, base) for name in geometry.object_names}


def _read_record(path: Path) -> dict | None:
    """A segment's cached training record; None (train again) when missing, foreign or corrupt."""
    try:
        record = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("kind") not in ("analytic", "network"):
        return None
    return record


def _loadable(path: Path) -> bool:
    """True if ``path`` is an ``.npz`` whose arrays read back (not truncated, not foreign)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                data[key]
        return True
    except MemoryError:
        raise
    except Exception:  # zipfile, zlib and numpy each raise their own kind on damaged bytes
        return False


def _trained_segment(record: dict, out: Path) -> TrainedSegment:
    """What export needs of a segment's training record (weights from ``train/segNNN.npz``)."""
    s = record["id"]
    segment = TrainedSegment(id=s, bounds=record["bounds"], samples=record["samples"],
                             coeff_mae=record["val_mae"], shaded_mae=record["shaded"], sizing=record.get("sizing"))  # fmt: skip
    if record["kind"] == "network":
        with np.load(out / record.get("weights", f"train/seg{s:03d}.npz")) as f:
            segment.arrays = dict(f)
        segment.architecture = record["arch"]
        segment.flops_per_fragment = record["flops_per_fragment"]
        segment.weight_bytes = record["weight_bytes"]
    return segment
