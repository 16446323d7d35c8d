"""Refinement: a build under its preset's absolute floor keeps working where the error is (issue 43).

The default sizing rule (:mod:`prt.train.networks.rightsize`, ``"vertex"``) stops each segment at a
margin over per-vertex PRT; where per-vertex PRT fails too (a building, a CAD assembly) that bar
says nothing.  So a build also has a floor: its **pooled held-out PSNR** (:func:`scene_psnr`: the
diffuse, tone-mapped radiance under the scene's lighting, :data:`prt.train.networks.rightsize.SCENE_LIGHT`,
of every segment's held-out samples together, :func:`prt.train.networks.rightsize.pooled_psnr`).
While it is under ``floor_db`` and the build's wall time (from its start) leaves room under
``build_budget`` for a refit (as long per step as that size's longest so far; one that does not fit is
passed over for the round's cheaper ones) and :data:`END_RESERVE_S`,
each round takes the segments holding most of the error (:func:`error_shares`: own samples, which
are area-uniform, times held-out MSE; the worst first, until half the error or :data:`PER_ROUND`
segments) that are under the floor themselves, and for each (:func:`plan_round`):

- **grows** its network one size up the build's ladder, past where the margin stopped it (and past
  its share of per-vertex PRT's bytes), trained :data:`REFIT_STEPS` times the build's steps (or the
  segment's own, where it has more); the larger size is kept where it is more accurate;
- **trains it longer** once growing stalls (the last size gained under :data:`MIN_GAIN_DB`) or the
  ladder's top is reached: the same size refitted with twice its steps, up to :data:`MAX_STEPS`
  times the build's, kept where more accurate, until a doubling gains under :data:`MIN_GAIN_DB`;
- **splits** it (:func:`prt.train.networks.segments.split_segment`) once neither growing nor longer
  training gains, while the build has fewer segments than its preset's cap
  (:data:`prt.train.presets.LEAF_CAP`); both halves are fitted at the parent's size, each at half its
  steps (not under the build's: as many passes over its half of the samples), and
  the split is kept where the halves' pooled held-out PSNR is above the whole's (else the segment
  stays whole and is not cut again).

The steps axis comes from the Duplex house (issue 43): its fits at the preset's then 1,000 steps of 4,096 are far
from converged (its five worst segments, ``studies/refine_steps.py``, ``docs/benchmarks/refine_steps_duplex.json``:
the same size at 3x the steps +1.5 to +2.8 dB; one size up at 1x -0.6 to +3.6 dB, at 2x the steps -0.0 to +5.1 dB).

No action is kept unless it is more accurate, so refinement does not lower a segment's PSNR.

It ends at the floor (``"floor"``), when the time is spent (``"time"``), or when no segment under
the floor can grow, train longer or be cut (``"ladder"``).  Stopping short, the report names the absolute PSNR,
the floor, and the segments holding most of the error with the objects whose samples they hold
(:func:`worst_segments`), and the segments worst at their own exposure (:func:`worst_exposed`): a
room lit through its windows is dark at exposure 1, so the area-weighted figure ranks it last, while
a view inside it is exposed for its light.  Refinement does not act on that second list: its head
on the Duplex is the large segments holding a facade's lit side and a room's dark one, and taking its
two worst each round as well (one scratch build, exposed then at the log-average) scored 21.12 / 30.59
dB inside / outside against the recorded 21.35 / 30.71 without; ranking every segment by its error at
its own exposure (the lit samples' median, :data:`prt.train.networks.rightsize.LIT_SHARE`; 2026-12-07,
one scratch Duplex build, AMD EPYC) scored 15.92 / 36.58 dB against 18.93 / 37.81 (held out 28.56
against 31.07 dB): 7 rounds instead of 13, a small segment dark at its own exposure grown to the
ladder's top and trained 8x.

Every fit goes through the fit cache (a refined segment's fits keyed by its samples), and the
rounds' decisions follow from the fitted PSNRs alone, so an interrupted build resumes: the rounds
done replay from the cache, and refinement goes on from there.  The refined segments' records and
weights are ``OUTDIR/refine/segNNN.json`` and ``.npz``; the precompute's own files are not changed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..runtime.files import atomic_save_npz, atomic_write_json
from ..runtime.segmentation import assign_segments, kd_arrays
from .fit_cache import fit_hash
from .networks.fit import DEFAULT_STEPS, FIT_THREADS
from .networks.network import Architecture
from .networks.rightsize import PSNR_CAP, SCENE_LIGHT, pooled_psnr, train_segment
from .networks.segments import split_segment, with_margin
from .presets import DEFAULT_QUALITY, LEAF_CAP

__all__ = ["REFINE_VERSION", "MIN_GAIN_DB", "REFIT_STEPS", "MAX_STEPS", "END_RESERVE_S", "PER_ROUND", "ERROR_SHARE", "WORST_SHOWN", "light_psnr", "scene_psnr", "error_shares",
           "plan_round", "worst_segments", "worst_exposed", "own_exposure_psnr", "exposed_order", "refine_build", "stop_lines", "scaled_steps"]  # fmt: skip

REFINE_VERSION = "refine-v1"  # part of a split segment's fit-cache key
MIN_GAIN_DB = 0.5  # a size up (or a doubling of the steps) that gains less: that axis is done for the segment
REFIT_STEPS = 2  # a grown network trains this many times the build's steps (its fits are far from converged at 1x)
MAX_STEPS = 8  # "longer" doubles a segment's steps up to this many times the build's
PER_ROUND = 4  # most segments acted on in one round
ERROR_SHARE = 0.5  # a round takes the worst segments until they hold this share of the error
WORST_SHOWN = 5  # segments a stop-short report names
MIN_SAMPLES = 256  # a segment is not cut below twice this many own samples (segment_samples' min_samples)
END_RESERVE_S = 10.0
"""Seconds of the build's budget no refit may run into: what comes after refinement (the export, about
1 s for 40-60 segments on two cores) and the command's own start and exit (0.9 s between ``prt-train``'s
wall time and the build's clock).  Without it the orchids' build ended 0.7 s past its 1200 s
(wall 1200.7 s, build clock 1199.8 s: its last refit ended a second before the budget)."""


def light_psnr(record: dict) -> float:
    """A segment's held-out PSNR under the scene's lighting (its worst map's where that is absent)."""
    psnr = (record.get("sizing") or {}).get("psnr_db") or {}
    return float(psnr[SCENE_LIGHT] if SCENE_LIGHT in psnr else min(psnr.values(), default=PSNR_CAP))


def scene_psnr(records: list[dict]) -> float:
    """The pooled held-out PSNR of all segments under the scene's lighting (the floor's measure)."""
    return round(pooled_psnr([(r["validation_samples"], light_psnr(r)) for r in records]), 3)


def error_shares(records: list[dict]) -> list[dict]:
    """Per segment, its share of the scene's error: own samples (area) x held-out MSE, worst first."""
    weights = [(r["id"], r["samples"] * 10.0 ** (-light_psnr(r) / 10.0), light_psnr(r)) for r in records]
    total = sum(w for _, w, _ in weights) or 1.0
    rows = [{"segment": int(s), "share": round(w / total, 4), "psnr_db": round(p, 3)} for s, w, p in weights]
    return sorted(rows, key=lambda r: (-r["share"], r["segment"]))


def plan_round(records: list[dict], state: dict, floor: float, ladder_size: int, can_split) -> list[tuple[int, str]]:
    """This round's ``(segment, "grow" | "longer" | "split")``: the worst segments under the floor
    (:func:`error_shares`) until they hold :data:`ERROR_SHARE` of the error, at most :data:`PER_ROUND`,
    each grown while a larger size is left and the last one gained, else trained longer while its steps
    are under :data:`MAX_STEPS` and the last doubling gained, else split where ``can_split(segment)``."""
    out, held = [], 0.0
    for row in error_shares(records):
        if len(out) >= PER_ROUND or (out and held >= ERROR_SHARE):
            break
        s = row["segment"]
        if row["psnr_db"] >= floor:
            continue
        st = state[s]
        grow = st["next"] < ladder_size and not st["stalled"]
        longer = st["index"] >= 0 and 2 * st["steps"] <= MAX_STEPS and not st["longer_stalled"]
        if grow:
            out.append((s, "grow"))
        elif longer:
            out.append((s, "longer"))
        elif can_split(s):
            out.append((s, "split"))
        elif st["next"] < ladder_size:  # cannot be cut: the sizes left are tried anyway
            out.append((s, "grow"))
        else:
            continue
        held += row["share"]
    return out


def own_exposure_psnr(record: dict) -> float | None:
    """A segment's held-out PSNR at its own samples' exposure (:func:`prt.train.networks.rightsize.exposed_psnr`:
    what a view it fills, exposed for it, shows); None where the record has none (analytic, older records)."""
    value = (record.get("sizing") or {}).get("exposed_psnr_db")
    return None if value is None else float(value)


def exposed_order(records: list[dict]) -> list[dict]:
    """The segments that have :func:`own_exposure_psnr`, worst first, whatever their area."""
    rows = [{"segment": int(r["id"]), "exposed_psnr_db": round(own_exposure_psnr(r), 3), "psnr_db": round(light_psnr(r), 3)}
            for r in records if own_exposure_psnr(r) is not None]  # fmt: skip
    return sorted(rows, key=lambda r: (r["exposed_psnr_db"], r["segment"]))


def _objects(segment: int, home: np.ndarray, object_ids: np.ndarray, names: list[str]) -> list[str]:
    """The (at most three) objects most of a segment's samples lie on, most first."""
    ids, n = np.unique(np.asarray(object_ids)[np.asarray(home) == segment], return_counts=True)
    order = np.argsort(-n, kind="stable")
    return [names[int(ids[i])] if 0 <= int(ids[i]) < len(names) else str(int(ids[i])) for i in order[:3]]


def worst_segments(records: list[dict], home: np.ndarray, object_ids: np.ndarray, names: list[str], count: int = WORST_SHOWN) -> list[dict]:
    """The ``count`` segments holding most of the error: id, share, PSNR (and at its own exposure, where known) and
    the objects of their samples (most first)."""
    out = []
    for row in error_shares(records)[:count]:
        exposed = own_exposure_psnr(records[row["segment"]])
        out.append({**row, **({"exposed_psnr_db": round(exposed, 3)} if exposed is not None else {}),
                    "objects": _objects(row["segment"], home, object_ids, names)})  # fmt: skip
    return out


def worst_exposed(records: list[dict], home: np.ndarray, object_ids: np.ndarray, names: list[str], count: int = WORST_SHOWN) -> list[dict]:
    """The ``count`` segments worst at their own exposure (:func:`exposed_order`) with their objects: where a view
    inside a dark room shows the most error, which the area-weighted :func:`worst_segments` ranks last."""
    return [{**row, "objects": _objects(row["segment"], home, object_ids, names)} for row in exposed_order(records)[:count]]


def stop_lines(refinement: dict) -> list[str]:
    """The summary's lines of a build that stopped under its floor (empty when it reached it)."""
    if refinement.get("met", True):
        return []
    why = {"time": f"the build's time ({refinement['budget_s']:.0f} s) spent", "ladder": "no segment under the floor could grow, train longer or be cut"}
    lines = [f"BELOW THE FLOOR: held-out PSNR {refinement['psnr_db']:.2f} dB (diffuse, under {refinement['light']}) < floor "
             f"{refinement['floor_db']:g} dB after {refinement['rounds']} refinement round(s); stopped: {why.get(refinement['ended'], refinement['ended'])}",
             "  the error is in (segment: share of the error, its PSNR, objects):"]  # fmt: skip
    for w in refinement["worst"]:
        lines.append(f"    segment {w['segment']}: {100 * w['share']:.0f} %, {w['psnr_db']:.2f} dB, {', '.join(w['objects'])}")
    if refinement.get("worst_exposed"):
        lines.append("  worst at their own exposure (a view they fill, exposed for them: dark rooms; segment: that PSNR, at exposure 1, objects):")
        for w in refinement["worst_exposed"]:
            lines.append(f"    segment {w['segment']}: {w['exposed_psnr_db']:.2f} dB, {w['psnr_db']:.2f} dB, {', '.join(w['objects'])}")
    return lines


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.int64).tobytes())
        h.update(b"|")
    return h.hexdigest()[:16]


def _ladder_index(record: dict, archs: list) -> int:
    """The ladder rung of a segment's network (-1: analytic or not on the ladder)."""
    if record["kind"] != "network":
        return -1
    a = record.get("arch") or {}
    for i, arch in enumerate(archs):
        if (arch.hidden, arch.layers, arch.pos_freqs) == (a.get("hidden"), a.get("layers"), a.get("pos_freqs")):
            return i
    return -1


@dataclasses.dataclass
class RefineJob:
    """What refinement needs of the build (:func:`prt.train.build._run_build`)."""

    spec: object
    out: Path
    tree: dict  # segments.json's dict
    samples: dict
    valid: dict
    members: list
    archs: list  # the build's full ladder, smallest first
    fit_settings: object
    lights: dict
    vertex: object
    data_key: str
    fit_cache: object  # (pre_key, segment, fit settings) -> a fit cache (prt.train.fit_cache._FitCache)
    object_names: list
    t_start: float
    log: object = print
    clock: object = time.perf_counter
    threads: int = 1  # refits run this many at a time (FIT_THREADS torch threads each)


def refine_build(job: RefineJob, records: list[dict]) -> tuple[list[dict], dict, dict]:
    """Refine while under the floor: ``(records, tree, refinement)`` (the report's ``refinement``)."""
    spec, log = job.spec, job.log
    floor, budget = float(spec.floor_db), float(spec.build_budget or 0.0)
    cap = max(LEAF_CAP.get(spec.quality or DEFAULT_QUALITY, LEAF_CAP[DEFAULT_QUALITY]), len(records))
    samples = {**job.samples, "segment": np.array(job.samples["segment"], copy=True)}
    valid = {**job.valid, "segment": np.array(job.valid["segment"], copy=True)}
    members, tree, records = list(job.members), dict(job.tree), [dict(r) for r in records]
    archs = [a for a in job.archs if isinstance(a, Architecture)]
    state = {r["id"]: _fresh(_ladder_index(r, archs), len(archs)) for r in records}
    unsplittable: set[int] = set()
    actions, rounds, start_psnr = [], 0, scene_psnr(records)

    spent: dict[str, float] = {}  # per size, the most seconds per step-multiple of its refits so far (a fit at 4x the steps: its seconds / 4)
    # A round's refits run as many at once as the build has threads, FIT_THREADS torch threads each (as the
    # build's fit stage; each fit seeds under a lock, prt.train.networks.fit.seeded).
    workers = max(1, job.threads // FIT_THREADS)

    def elapsed() -> float:
        return job.clock() - job.t_start

    def cost(steps: int, arch) -> float:
        """Seconds of one refit of ``arch`` at ``steps`` times the build's steps: as long per step as that size's
        longest so far (any size's, for a size not fitted yet).  (The mean let the orchids' build end 2.4 s past
        its 1200 s: its last refits, larger networks on more samples, took longer than the mean.)"""
        per = spent.get(arch.label()) if arch is not None else None
        return steps * (per if per is not None else max(spent.values(), default=0.0))

    def left(fits: int, steps: int = 1, arch=None, pending=()) -> bool:
        """Time is left for ``fits`` more refits of ``arch`` at ``steps`` times the build's steps after the
        ``pending`` ones (``(steps, arch)`` pairs), all run ``workers`` at a time: none is started that would end
        past the budget (:func:`together_wall`)."""
        costs = [cost(n, a) for n, a in pending] + [cost(steps, arch)] * fits
        return elapsed() + together_wall(costs, workers) + END_RESERVE_S < budget

    def together(calls: list) -> list:
        """The results of ``calls`` (no-argument functions), run ``workers`` at a time, in order."""
        if len(calls) <= 1 or workers == 1:
            return [call() for call in calls]
        with ThreadPoolExecutor(max_workers=min(workers, len(calls)), thread_name_prefix="prt-refit") as pool:
            return list(pool.map(lambda call: call(), calls))

    def can_split(s: int) -> bool:
        return len(records) < cap and s not in unsplittable and records[s]["samples"] >= 2 * MIN_SAMPLES

    def fit(s: int, arch, steps: int, like: dict, changed: bool, round_: int, action: str) -> dict:
        residual = bool((like.get("residual") or {}).get("used"))
        sub = dataclasses.replace(spec, residual="on" if residual else "off", analytic=False)  # under the floor: a network
        if not spec.vertex_rule() or job.vertex is None:
            keep = {"hidden": arch.hidden, "layers": arch.layers, "pos_freqs": arch.pos_freqs}
            sub = dataclasses.replace(sub, fixed=keep, match=None, target_db=None, vertex_margin=None)
        own = np.flatnonzero(samples["segment"] == s)
        pre_key = fit_hash(job.data_key, REFINE_VERSION, _digest(members[s], own, np.flatnonzero(valid["segment"] == s))) if changed else job.data_key
        settings = scaled_steps(job.fit_settings, steps)
        t0 = job.clock()
        record = train_segment(sub, s, samples, valid, members[s], [arch], settings, job.lights, False, log, job.fit_cache(pre_key, s, settings),
                               vertex=job.vertex if spec.vertex_rule() else None)  # fmt: skip
        spent[arch.label()] = max(spent.get(arch.label(), 0.0), (job.clock() - t0) / steps)
        record["refined"] = {"round": round_, "action": action, "steps": steps, "from": like.get("arch_label", like["kind"]),
                             "from_psnr_db": round(light_psnr(like), 3), "psnr_db": round(light_psnr(record), 3)}  # fmt: skip
        record["sizing"]["reason"] += f"; refined ({action}, round {round_}) toward the floor {floor:g} dB"
        return record

    def store(record: dict) -> dict:
        s = record["id"]
        folder = job.out / "refine"
        folder.mkdir(parents=True, exist_ok=True)
        if "arrays" in record:
            atomic_save_npz(folder / f"seg{s:03d}.npz", **record.pop("arrays"))
            record["weights"] = f"refine/seg{s:03d}.npz"
        atomic_write_json(folder / f"seg{s:03d}.json", record)
        return record

    ended = "floor"
    while archs:  # (a grid build has no frequency ladder to grow or refit on: it reports where it stands)
        psnr = scene_psnr(records)
        if psnr >= floor:
            break
        if not left(1):
            ended = "time"
            break
        todo = plan_round(records, state, floor, len(archs), can_split)
        if not todo:
            ended = "ladder"
            break
        rounds += 1
        log(f"refine round {rounds}: held-out {psnr:.2f} dB < floor {floor:g} dB ({elapsed():.0f} of {budget:.0f} s); "
            + ", ".join(f"{a} segment {s}" for s, a in todo))  # fmt: skip
        ran, refits = 0, []  # refits: this round's grow and longer actions not run yet, (segment, action, rung, steps)

        def run_refits() -> None:
            """The round's pending grow / longer refits, at once; their outcomes applied in the round's order."""
            fitted = together([lambda r=r: fit(r[0], archs[r[2]], r[3], records[r[0]], state[r[0]]["changed"], rounds, r[1]) for r in refits])
            for (s, action, j, steps), record in zip(refits, fitted):
                before, st = records[s], state[s]
                gain = light_psnr(record) - light_psnr(before)
                if action == "grow":
                    st["next"] = j + 1
                    st["stalled"] = gain < MIN_GAIN_DB
                else:
                    st["longer_stalled"] = gain < MIN_GAIN_DB
                if gain > 0:
                    records[s] = store(record)
                    st["index"], st["steps"] = j, steps
                actions.append({"round": rounds, "segment": s, "action": action, "to": archs[j].label(), "steps": steps, "kept": gain > 0,
                                "psnr_db": [round(light_psnr(before), 3), round(light_psnr(record), 3)]})  # fmt: skip
            refits.clear()

        for s, action in todo:
            before = records[s]
            st = state[s]
            # a split's halves train half the whole's steps each (as many passes over their half of the samples)
            steps = {"grow": max(st["steps"], REFIT_STEPS), "longer": 2 * st["steps"]}.get(action, max(1, st["steps"] // 2))
            j = {"grow": st["next"], "longer": st["index"]}.get(action, st["index"] if st["index"] >= 0 else (len(archs) - 1) // 2)
            if not left(2 if action == "split" else 1, steps, archs[j], [(r[3], archs[r[2]]) for r in refits]):
                continue  # not in the time left: a cheaper action of this round may be
            ran += 1
            if action in ("grow", "longer"):
                refits.append((s, action, j, steps))
                continue
            run_refits()  # a split changes the samples' segments: the refits before it run first
            saved = (tree, samples["segment"], valid["segment"].copy(), members[s])
            cut = split_segment(tree, samples["points"], samples["object_ids"], samples["segment"], s, min_samples=MIN_SAMPLES)
            if cut is None:
                unsplittable.add(s)
                continue
            tree, samples["segment"] = cut
            new = len(tree["segments"]) - 1
            _reassign_validation(tree, valid, s, new)
            members[s] = with_margin(samples["points"], samples["normals"], samples["segment"], s, tree["delta"])
            members.append(with_margin(samples["points"], samples["normals"], samples["segment"], new, tree["delta"]))
            for g in (s, new):
                tree["segments"][g]["margin_samples"] = int(len(members[g]) - tree["segments"][g]["samples"])
            arch = archs[j]
            records.append(None)  # the new segment's place
            halves = together([lambda g=g: fit(g, arch, steps, before, True, rounds, "split") for g in (s, new)])
            kept = scene_psnr(halves) > light_psnr(before)  # the two halves' pooled held-out PSNR against the whole's
            actions.append({"round": rounds, "segment": s, "action": "split", "into": [s, new], "size": arch.label(), "steps": steps, "kept": kept,
                            "psnr_db": [round(light_psnr(before), 3), *(round(light_psnr(h), 3) for h in halves)]})  # fmt: skip
            if not kept:  # no better in two: the segment stays whole, and is not cut again
                tree, samples["segment"], valid["segment"], members[s] = saved
                members.pop()
                records.pop()
                unsplittable.add(s)
                continue
            for g, half in zip((s, new), halves):
                records[g] = store(half)
                state[g] = {**_fresh(st["index"], len(archs)), "steps": steps, "changed": True}
        run_refits()
        if not ran:
            ended = "time"
            break
    else:
        ended = "floor" if start_psnr >= floor else "ladder"
    psnr = scene_psnr(records)
    refinement = {"floor_db": floor, "light": SCENE_LIGHT, "psnr_db": psnr, "start_psnr_db": start_psnr, "met": psnr >= floor,
                  "ended": ended, "rounds": rounds, "budget_s": budget, "elapsed_s": round(elapsed(), 1), "segments": len(records),
                  "actions": actions}  # fmt: skip
    if psnr < floor:
        refinement["worst"] = worst_segments(records, samples["segment"], samples["object_ids"], job.object_names)
        refinement["worst_exposed"] = worst_exposed(records, samples["segment"], samples["object_ids"], job.object_names)
    if rounds:
        log(f"refinement: {rounds} round(s), held-out {start_psnr:.2f} -> {psnr:.2f} dB (floor {floor:g} dB), {len(records)} segments")
    return records, tree, refinement


def together_wall(costs: list[float], workers: int) -> float:
    """A bound on the wall time of jobs of ``costs`` seconds run ``workers`` at a time in any order, each
    started when a worker frees: ``sum / w + max (w - 1) / w`` (one worker: the sum)."""
    if not costs:
        return 0.0
    return sum(costs) / workers + max(costs) * (workers - 1) / workers


def _fresh(index: int, ladder_size: int) -> dict:
    """A segment's refinement state: its rung, the next rung to try, whether growing stalled, its steps (a multiple of
    the build's), whether doubling them stalled, whether its samples changed."""
    return {"index": index, "next": index + 1 if index >= 0 else (ladder_size - 1) // 2, "stalled": False, "steps": 1,
            "longer_stalled": False, "changed": False}  # fmt: skip


def scaled_steps(settings, times: int):
    """``settings`` (:class:`prt.train.networks.fit.FitSettings`) training ``times`` as long: its steps (the
    default's where unset), or its epochs in an epoch-based run, and its time budget per fit."""
    if times == 1:
        return settings
    if settings.steps is None and settings.epochs is not None:
        longer = {"epochs": settings.epochs * times}
    else:
        longer = {"steps": (DEFAULT_STEPS if settings.steps is None else settings.steps) * times}
    if settings.max_seconds is not None:
        longer["max_seconds"] = settings.max_seconds * times
    return dataclasses.replace(settings, **longer)


def _reassign_validation(tree: dict, valid: dict, s: int, new: int) -> None:
    """The held-out samples of segment ``s`` after its split: by the new tree, to ``s`` or ``new``."""
    mask = valid["segment"] == s
    if not mask.any():
        return
    bounds = np.array([g["bounds"] for g in tree["segments"]], dtype=np.float64)
    roots = {int(k): int(v) for k, v in tree["roots"].items()}
    seg = assign_segments(kd_arrays(tree["nodes"]), roots, np.asarray(tree["leaf_segment"]), bounds,
                          np.asarray(valid["points"], dtype=np.float64)[mask], np.asarray(valid["object_ids"])[mask])  # fmt: skip
    valid["segment"][np.flatnonzero(mask)] = np.where(np.isin(seg, (s, new)), seg, s)
