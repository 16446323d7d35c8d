"""Where does the build's indirect transfer differ from the benchmark's bounce reference (issue #13)?

Sample level, no networks: the build's ground-truth indirect transfer of its validation samples
(``T_1 + ... + T_N`` from the bounce stage's cached rays, :func:`prt.train.transport.interreflection.bounce_terms`)
against :func:`prt.bench.bounce_reference.indirect_transfer` evaluated at the same points, both
shaded under an env map's SH (mean over RGB of ``T . L``); split by object and by distance to
the nearest edge of the box.  Also the first bounce alone (``--split``: build T_1 vs reference with
``bounces=1``), and the build's estimator with the exact-hit variant (``--exact``: the first bounce
gathered with the direct transfer ray traced at the exact hit point, the reference's rule) to
separate the nearest-sample lookup from everything else.

    .venv/bin/python studies/indirect_bias.py /tmp/loss/cb/b2 --count 5000 --split --exact --retrace /tmp/bias/retrace

Prints a table; writes ``/tmp/bias/indirect_bias.npz`` (per-sample values) unless ``--out``.
Pixel level (``--view V``: the built networks' indirect against the reference at view V, and
optionally a reference cached before the fix):

    .venv/bin/python studies/indirect_bias.py /tmp/loss/cb/b2 --view 0 \
        --old-indirect /tmp/loss/cb/reference/v0-256-indirect-b2-s0-85986329a8ca.npz --estimator-rays 128

``--gap``: the first bounce of the samples in the light/ceiling gap; ``--timing``: the search's cost.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


FIRST = ("build T1", "build rays, exact T0 (b=1)")  # compared with the reference's first bounce


def load_found(cache: Path, count_train: int, count_valid: int):
    """The build's cached bounce rays {"train", "validation"} (chunks of (2048, 2, M) int32)."""
    from prt.train.transport.interreflection import BounceRays

    found = {}
    for name, count in (("train", count_train), ("validation", count_valid)):
        folder = sorted(cache.glob(f"bounce-{name}-*"))
        if len(folder) != 1:
            sys.exit(f"{cache}: expected one bounce-{name}-* chunk store, found {len(folder)}")
        chunks = [np.load(p) for p in sorted(folder[0].glob("chunk_*.npy"))]
        data = np.concatenate(chunks)[:count]
        if len(data) != count:
            sys.exit(f"{folder[0]}: {len(data)} rows, expected {count}")
        found[name] = BounceRays(data[:, 0].astype(np.int64), data[:, 1].astype(np.int64))
    return found


def edge_distance(points, lo, hi):
    """Distance of each point to the nearest of the box's edges (two coordinates at a bound)."""
    d = np.minimum(np.abs(points - lo), np.abs(points - hi))  # (P, 3) to each pair of planes
    d.sort(axis=1)
    return d[:, 1]  # on a wall one coordinate is ~0; the second smallest is the distance to an edge


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("build", type=Path)
    p.add_argument("--count", type=int, default=1500, help="validation samples compared")
    p.add_argument("--envmap", default="potsdamer")
    p.add_argument("--reference-cache", type=Path, default=Path("/tmp/bias/reference"), help="where the reference's higher-bounce samples are cached")
    p.add_argument("--retrace", type=Path, default=None, metavar="DIR",
                   help="also the build's estimator with its rays traced again by the current code (chunk stores in DIR)")
    p.add_argument("--hit-rays", type=int, default=64)
    p.add_argument("--rays", type=int, default=128, help="direct-transfer rays at each reference hit")
    p.add_argument("--split", action="store_true", help="also the first bounce alone")
    p.add_argument("--exact", action="store_true", help="also the build's rays with the direct transfer traced at the exact hit")
    p.add_argument("--out", type=Path, default=Path("/tmp/bias/indirect_bias.npz"))
    p.add_argument("--view", type=int, default=None, help="instead: the networks' indirect at this view against the reference (pixels)")
    p.add_argument("--estimator-rays", type=int, default=0, help="with --view: also the build's estimator at the pixels, with this many rays")
    p.add_argument("--old-indirect", type=Path, default=None, help="with --view: a reference indirect cached before the fix, compared too")
    p.add_argument("--timing", action="store_true", help="instead: time the bounce rays' search, PLANE_CANDIDATES 1 (the old rule) vs the default")
    p.add_argument("--gap", action="store_true", help="instead: first-bounce transfer of the samples in the light/ceiling gap (build and reference)")
    args = p.parse_args(argv)
    if args.gap:
        return gap_check(args.build, args.reference_cache, args.envmap)
    if args.timing:
        return timing(args.build)
    if args.view is not None:
        return view_check(args.build, args.view, args.reference_cache, args.old_indirect, args.envmap, args.estimator_rays)

    from prt.bench.bounce_reference import face_albedo, higher_bounce_samples, indirect_transfer
    from prt.bench.reference import load_scene_geometry
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.envmaps import bundled_envmap_path
    from prt.runtime.manifest import load_manifest
    from prt.train import compute_transfer
    from prt.train.transport.interreflection import bounce_terms
    from prt.train.transport.transfer import make_tracer

    manifest = load_manifest(args.build / "scene.json")
    geometry, info = load_scene_geometry(manifest)
    tracer = make_tracer(geometry)
    record = manifest.raw["interreflection"]
    bounces = int(record["bounces"])
    albedo = face_albedo(record["albedos"], geometry)
    L = load_envmap_sh(bundled_envmap_path(args.envmap), 4)
    pre = args.build / "precompute"
    samples, valid = dict(np.load(pre / "samples.npz")), dict(np.load(pre / "validation.npz"))
    found = load_found(pre / "cache", len(samples["points"]), len(valid["points"]))
    t0 = time.perf_counter()
    terms = {b: v for b, _, v in bounce_terms(found, albedo, samples["transfer"], bounces)}
    print(f"build bounce terms: {time.perf_counter() - t0:.1f} s")

    rng = np.random.default_rng(1)
    pick = np.sort(rng.choice(len(valid["points"]), min(args.count, len(valid["points"])), replace=False))
    pts, nrm = valid["points"][pick].astype(np.float64), valid["normals"][pick].astype(np.float64)
    obj = valid["object_ids"][pick]
    build = {b: t[pick] for b, t in terms.items()}
    higher = None
    if bounces >= 2:
        higher = higher_bounce_samples(geometry, tracer, albedo, bounces, rays=256, cache=args.reference_cache, geometry_id=info["checksum"])
    t0 = time.perf_counter()
    ref = indirect_transfer(geometry, tracer, pts, nrm, albedo, bounces, hit_rays=args.hit_rays, rays=args.rays, higher=higher, seed=7)
    print(f"reference ({len(pick)} points, {args.hit_rays} x {args.rays} rays): {time.perf_counter() - t0:.1f} s")
    rows = {"build T1..TN": sum(build.values()), "reference": ref}
    if args.retrace is not None:  # the current nearest-sample rule on the build's own samples and seeds
        from prt.train.transport.interreflection import trace_stage

        t0 = time.perf_counter()
        again = trace_stage(geometry.mesh, args.retrace, samples, valid, rays=found["train"].nearest.shape[1], seed=0, key="retrace",
                            threads=1, progress=False)  # fmt: skip
        changed = float((again["validation"].nearest != found["validation"].nearest).mean())
        print(f"retraced in {time.perf_counter() - t0:.1f} s; validation hits whose sample changed: {changed:.2%}")
        retraced = {b: v for b, _, v in bounce_terms(again, albedo, samples["transfer"], bounces)}
        rows["build retraced T1..TN"] = sum(t[pick] for t in retraced.values())
    if args.split:
        rows["build T1"] = build[1]
        rows["reference b=1"] = indirect_transfer(geometry, tracer, pts, nrm, albedo, 1, hit_rays=args.hit_rays, rays=args.rays, seed=7)
    if args.exact:  # the build's own rays (validation stream), T_0 traced at the exact hit instead of the nearest sample's
        from prt.train.transport.interreflection import BounceJob

        job = BounceJob(tracer, samples["points"], samples["normals"], rays=found["validation"].nearest.shape[1], seed=0, stream=1, workers=1)
        rows["build rays, exact T0 (b=1)"] = exact_first_bounce(job, geometry, tracer, pts, nrm, albedo, args.rays, compute_transfer)

    def shade(t):
        return np.einsum("pkc,kc->p", np.asarray(t, dtype=np.float64), L) / 3.0

    lo, hi = geometry.mesh.bounds
    edge = edge_distance(pts, lo, hi)
    names = list(geometry.object_names)
    shaded = {k: shade(v) for k, v in rows.items()}
    base = shaded["reference"]
    print(f"\n{args.envmap}: mean shaded indirect (T.L, mean of RGB); ratio to the reference (b={bounces})")
    inside = np.einsum("pc,pc->p", nrm, 0.5 * (lo + hi) - pts) > 0  # the side facing the box's centre
    groups = [("all", np.ones(len(pick), bool)), ("inside", inside), ("outside", ~inside)]
    groups += [(names[o], inside & (obj == o)) for o in np.unique(obj)]
    groups += [(f"in, edge<{e}", inside & (edge < e)) for e in (0.05, 0.15)] + [("in, edge>=0.15", inside & (edge >= 0.15))]
    header = f"{'group':>16} {'n':>5} " + " ".join(f"{k:>26}" for k in shaded)
    print(header)
    for label, s in groups:
        if not s.any():
            continue
        cells = []
        for k, v in shaded.items():
            ref_k = shaded["reference b=1"] if k in FIRST and "reference b=1" in shaded else base
            cells.append(f"{v[s].mean():.5f} ({v[s].mean() / max(ref_k[s].mean(), 1e-12):.3f})")
        print(f"{label:>16} {int(s.sum()):5d} " + " ".join(f"{c:>26}" for c in cells))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(args.out, pick=pick, objects=obj, edge=edge, inside=inside, **{k.replace(" ", "_"): v for k, v in shaded.items()})
    print(f"wrote {args.out}")


def exact_first_bounce(job, geometry, tracer, points, normals, albedo, rays, compute_transfer):
    """First bounce with the build's ray directions and hit faces, T_0 ray traced at the exact hit (twin of the reference's rule)."""
    from prt.train.transport.transfer import _unit, orthonormal_frames

    points, normals = np.asarray(points, np.float64), _unit(np.asarray(normals, np.float64))
    rng = np.random.default_rng(3)
    frames = orthonormal_frames(normals, rng.uniform(0.0, 2.0 * np.pi, len(points))).astype(np.float32)
    dirs = np.matmul(job.local[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat((points + tracer.offset * normals).astype(np.float32), job.rays, axis=0)
    result = tracer._scene.run(origins, dirs, output=1)
    faces = result["primID"].astype(np.int64)
    hit = faces >= 0
    q = origins[hit] + result["tfar"][hit, None] * dirs[hit]
    ng = _unit(result["Ng"][hit].astype(np.float64))
    ng *= -np.sign(np.einsum("qc,qc->q", ng, dirs[hit].astype(np.float64)))[:, None]
    t = np.zeros((len(origins), 16, 3))
    t[hit] = compute_transfer(geometry, q, ng, rays=rays, seed=11, tracer=tracer).astype(np.float64)[:, :, None]
    w = np.where(hit[:, None], albedo[np.where(hit, faces, 0)], 0.0)
    return np.einsum("pmc,pmkc->pkc", w.reshape(len(points), job.rays, 3), t.reshape(len(points), job.rays, 16, 3)) / job.rays


def view_check(build: Path, view: int, cache: Path, old: Path | None, envmap: str, estimator_rays: int = 0) -> None:
    """Pixel level at ``view``: the networks' indirect ``T.L`` against the (current) reference's, mean ratio per object."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from cornell_bounces import object_albedos, pixel_objects

    from prt.bench.bounce_reference import cached_indirect, face_albedo, higher_bounce_samples
    from prt.bench.reference import load_scene_geometry
    from prt.runtime.camera import Camera, orbit_views
    from prt.runtime.renderer import Renderer, Scene
    from prt.train.transport.transfer import make_tracer

    scene = Scene.load(build / "scene.json")
    geometry, info = load_scene_geometry(scene.manifest)
    tracer = make_tracer(geometry)
    names = list(geometry.object_names)
    receivers = object_albedos(scene.manifest, geometry)
    record = scene.manifest.raw["interreflection"]
    bounces = int(record["bounces"])
    cam = orbit_views(Camera.from_manifest(scene.manifest.camera), 3)[view]
    with Renderer(scene, 256, 256, backend="onnx") as r:
        r.set_envmap(envmap)
        for n in names:
            r.set_material("diffuse", albedo=receivers[n], object=n)
        r.set_camera_object(cam)
        tnet = r.render_transfer()
        g = r.gbuffer_image()
        L = r.lighting.sh.astype(np.float64)
    cov = g.covered
    pts, nrm = g.position[cov], g.normal[cov]
    albedo = face_albedo(record["albedos"], geometry)
    higher = higher_bounce_samples(geometry, tracer, albedo, bounces, rays=256, cache=cache, geometry_id=info["checksum"]) if bounces >= 2 else None
    t0 = time.perf_counter()
    ref, _ = cached_indirect(cache, f"v{view}-256", geometry, tracer, pts, nrm, albedo, bounces, geometry_id=info["checksum"], higher=higher, rays=128)
    print(f"view {view}: {int(cov.sum())} pixels, reference indirect in {time.perf_counter() - t0:.1f} s")
    tn = tnet[cov].astype(np.float64)
    net = tn[:, 16:].reshape(len(tn), 3, 16).transpose(0, 2, 1)
    rows = {"network": net, "reference": ref}
    if old is not None:
        with np.load(old) as data:
            rows["old reference"] = data["indirect"]
    if estimator_rays:  # the build's own estimator at the pixels (current code): separates the ground truth from the fit
        from prt.train.transport.interreflection import BounceJob, BounceRays, bounce_matrices, bounce_terms

        pre = build / "precompute"
        samples = dict(np.load(pre / "samples.npz"))
        found = load_found(pre / "cache", len(samples["points"]), len(np.load(pre / "validation.npz")["points"]))
        direct = np.repeat(samples["transfer"].astype(np.float64)[:, :, None], 3, axis=2)
        gathered = direct + sum(t for b, t, _ in bounce_terms(found, albedo, samples["transfer"], bounces - 1)) if bounces >= 2 else direct
        job = BounceJob(tracer, samples["points"], samples["normals"], rays=estimator_rays, seed=0, stream=3, workers=1)
        parts = [job.chunk(pts[i : i + 4096], nrm[i : i + 4096], c) for c, i in enumerate(range(0, len(pts), 4096))]
        rays_pix = BounceRays(np.concatenate([a for a, _ in parts]), np.concatenate([b for _, b in parts]))
        w = bounce_matrices(rays_pix, albedo, targets=len(samples["points"]))
        rows["build estimator"] = np.stack([w[c] @ gathered[:, :, c] for c in range(3)], axis=2)
    objects = pixel_objects(tracer, geometry, cam.eye, pts)
    shaded = {k: np.einsum("pkc,kc->p", np.asarray(v, np.float64), L) / 3.0 for k, v in rows.items()}
    print(f"{envmap}, view {view}: mean indirect T.L (mean of RGB); ratio: network / each other row")
    for label, s in [("all", np.ones(len(pts), bool))] + [(names[o], objects == o) for o in np.unique(objects) if o >= 0]:
        cells = " ".join(f"{k} {v[s].mean():.5f}" for k, v in shaded.items())
        ratio = " ".join(f"{shaded['network'][s].mean() / max(shaded[k][s].mean(), 1e-12):.3f}" for k in shaded if k != "network")
        print(f"  {label:>10} {int(s.sum()):6d}  {cells}  ratio {ratio}")


def gap_check(build: Path, cache: Path, envmap: str) -> None:
    """Mean shaded T_1 of the samples above and below the light quad (Cornell box): the build's
    training samples (its cached rays) and the reference's independent samples (``H``, bounces = 2)."""
    from prt.bench.bounce_reference import face_albedo, higher_bounce_samples
    from prt.bench.reference import load_scene_geometry
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.envmaps import bundled_envmap_path
    from prt.runtime.manifest import load_manifest
    from prt.train.transport.interreflection import bounce_terms
    from prt.train.transport.transfer import make_tracer

    manifest = load_manifest(build / "scene.json")
    geometry, info = load_scene_geometry(manifest)
    albedo = face_albedo(manifest.raw["interreflection"]["albedos"], geometry)
    L = load_envmap_sh(bundled_envmap_path(envmap), 4)
    pre = build / "precompute"
    samples = dict(np.load(pre / "samples.npz"))
    found = load_found(pre / "cache", len(samples["points"]), len(np.load(pre / "validation.npz")["points"]))
    t1 = next(iter(bounce_terms(found, albedo, samples["transfer"], 1)))[1]
    hp, hn, h = higher_bounce_samples(geometry, make_tracer(geometry), albedo, 2, rays=256, cache=cache, geometry_id=info["checksum"])
    light = samples["points"][samples["object_ids"] == list(geometry.object_names).index("light")]
    lo, hi = light.min(axis=0), light.max(axis=0)
    ceiling_y = float(samples["points"][samples["object_ids"] == list(geometry.object_names).index("ceiling"), 1].max())
    print(f"{envmap}: mean shaded T_1 of samples within the light's footprint (light y {lo[1]:.4f}, ceiling y {ceiling_y:.4f})")
    for label, P, N, T in (("build", samples["points"], samples["normals"], t1), ("reference H", hp, hn, h)):
        foot = (P[:, 0] > lo[0]) & (P[:, 0] < hi[0]) & (P[:, 2] > lo[2]) & (P[:, 2] < hi[2])
        shaded = np.einsum("pkc,kc->p", np.asarray(T, np.float64), L) / 3.0
        for name, y, side in (("ceiling, facing down (in the gap)", ceiling_y, -1), ("light top (in the gap)", lo[1], 1), ("light underside", lo[1], -1)):
            s = foot & (np.abs(P[:, 1] - y) < 2e-3) & (np.sign(N[:, 1]) == side)
            print(f"  {label:>11} {name:>34}: {int(s.sum()):5d} samples, mean {shaded[s].mean():.4f}, p90 {np.quantile(shaded[s], 0.9):.4f}")


def timing(build: Path, repeats: int = 3) -> None:
    """Seconds of :meth:`BounceJob.chunk` over the build's validation samples (one thread), k = 1 vs the default."""
    import prt.train.transport.interreflection as ir
    from prt.bench.reference import load_scene_geometry
    from prt.runtime.manifest import load_manifest
    from prt.train.transport.transfer import make_tracer

    geometry, _ = load_scene_geometry(load_manifest(build / "scene.json"))
    pre = build / "precompute"
    samples, valid = np.load(pre / "samples.npz"), np.load(pre / "validation.npz")
    job = ir.BounceJob(make_tracer(geometry), samples["points"], samples["normals"], seed=0, stream=1, workers=1)
    default = ir.PLANE_CANDIDATES
    best = {}
    for _ in range(repeats):  # interleaved, best of `repeats`
        for k in (1, default):
            ir.PLANE_CANDIDATES = k
            t0 = time.perf_counter()
            for c, i in enumerate(range(0, len(valid["points"]), 2048)):
                job.chunk(valid["points"][i : i + 2048], valid["normals"][i : i + 2048], c)
            best[k] = min(best.get(k, np.inf), time.perf_counter() - t0)
    ir.PLANE_CANDIDATES = default
    print(f"bounce rays of {len(valid['points'])} samples x {job.rays}: k=1 {best[1]:.2f} s, k={default} {best[default]:.2f} s "
          f"(x{best[default] / best[1]:.2f})")


if __name__ == "__main__":
    main()
