"""The results pages and the README's results table, from the recorded files in ``docs/benchmarks/``.

Every figure shown comes from a recorded file, next to that file's date, command and machine:
its ``provenance`` (:mod:`prt.bench.provenance`), else what the file itself records (``created``,
``date``, ``command``, ``argv``, ``machine``, ``cpu``), else the date it entered the repository
(``docs/benchmarks/_history.json``, backfilled from git history) and "not recorded" for the rest.
A file's own Markdown table (``NAME.md`` beside ``NAME.json``, written by the tool that measured
it) is shown as it is; otherwise its figures are listed from the JSON.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

__all__ = ["result_pages", "readme_with_table", "mkdocs_with_nav", "provenance_of", "PAGES"]

# page slug -> (title, what it holds, file-name prefixes); the first page whose prefix matches wins
PAGES = [
    ("gpu", "GPU", "Frame times and fits on a GPU (the prepared GPU check).", ("gpu",)),
    ("web", "Web page", "The WebGL2 page against the Python GLSL backend; the scene in three.js against the page.", ("web", "three")),
    ("presets", "Build presets and defaults", "Build time and error of the `--quality` presets and of the default build on unseen meshes.",
     ("presets", "defaults", "vertex_estimate")),
    ("fidelity", "Independent reference", "Our reference and builds against Mitsuba 3; the bounce rule it led to.", ("mitsuba", "entering")),
    ("paper", "Paper table", "The paper's table: networks against vertex and texture PRT, per mesh.", ("paper",)),
    ("frame-rate", "Frame rate", "Frame times of the backends, screen-space interpolation, precision variants, shader compiles.",
     ("demo_fps", "runtime", "interpolation", "glsl", "network_profile", "int8", "onnx_graph", "many_segments")),
    ("build-cost", "Build cost", "Precompute, training and cluster timings; quick builds.",
     ("precompute", "train_", "cluster", "spot_quick", "creature_steps")),
    ("networks", "Networks and sizing", "Network size, encodings, residual networks, losses, sampling and segment studies.",
     ("many_networks", "grid_encoding", "residual", "loss_weighting", "loss_l2", "adaptive", "split_rule", "segment_error_share", "segment_margin", "daffodil", "fit_batch")),
    ("interreflection", "Interreflection", "Bounces: depth, the Cornell box, against vertex PRT with the same bounces.",
     ("bounce_depth", "cornell", "interreflection", "vertex_same_bounces", "vertex_bounces", "dering")),
    ("texture", "Texture PRT", "Transfer textures: atlases, seams, bounces.", ("texture",)),
    ("sdf", "SDF and mixed scenes", "Neural SDFs, tracing, mixed scenes.", ("neural_sdf", "mixed_scene")),
    ("deformable", "Deformable objects", "Deformable characters and sheets per frame.", ("deform",)),
    ("scenes", "Scenes and probe grids", "The networks against the engines' L2 SH probe grid: equal bytes, engine density, light leaking.",
     ("probe_grid", "scenes_real", "nearest_samples", "refine_steps", "view_error", "cutout", "bounce_lookup")),
]
OTHER = ("other", "Other records", "Recorded files no other page takes.", ())


def _page_of(name: str) -> tuple:
    for page in PAGES:
        if name.startswith(page[3]):
            return page
    return OTHER


def _history(root: Path) -> dict:
    path = root / "docs" / "benchmarks" / "_history.json"
    return json.loads(path.read_text(encoding="utf-8")).get("files", {}) if path.is_file() else {}


def _machine_text(machine) -> str | None:
    if isinstance(machine, str):
        return machine
    if not isinstance(machine, dict):
        return None
    cpu = machine.get("cpu")
    if not cpu:
        return None
    parts = [str(cpu)]
    if machine.get("cores"):
        parts.append(f"{machine['cores']} cores")
    if machine.get("extensions"):
        parts.append(" ".join(machine["extensions"]))
    for key in ("gl_renderer", "gpu", "renderer"):
        if machine.get(key):
            parts.append(str(machine[key]))
    return ", ".join(parts)


def _command_text(data: dict) -> str | None:
    for key in ("command", "commands", "argv", "cmd"):
        value = data.get(key)
        if isinstance(value, str) and value:
            return value
        if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
            return " ".join(value) if key == "argv" else "; ".join(value)
        if isinstance(value, dict) and value:
            return "; ".join(f"{k}: {v}" for k, v in value.items() if isinstance(v, str))
    return None


def provenance_of(name: str, data: dict, history: dict) -> dict:
    """``{"date", "command", "machine"}`` of a recorded file, each a string (or a "not recorded" note)."""
    prov = data.get("provenance") if isinstance(data.get("provenance"), dict) else {}
    date = prov.get("date") or data.get("created") or data.get("date")
    if not date and isinstance(data.get("machine"), dict):
        date = data["machine"].get("date")
    if not date and name in history:
        date = f"{history[name]['added']} (entered the repository; the file records no date)"
    command = prov.get("command") or _command_text(data)
    if not command and data.get("tool") == "prt-bench":
        command = "prt-bench (its arguments are in the file's settings)"
    machine = _machine_text(prov.get("machine")) or _machine_text(data.get("machine"))
    if not machine and data.get("cpu"):
        machine = f"{data['cpu']}, {data.get('cores', '?')} cores"
    return {
        "date": str(date) if date else "not recorded",
        "command": command or "not recorded",
        "machine": machine or "not recorded (one of the project's 2-core CPU machines, no GPU, Mesa llvmpipe)",
    }


def _fmt(value) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e5 else f"{value:.0f}"
    return str(value)


def _numeric_leaves(data, prefix="", out=None, limit=60):
    out = [] if out is None else out
    if len(out) >= limit:
        return out
    if isinstance(data, dict):
        for key, value in data.items():
            if key in ("provenance", "settings", "machine", "command", "commands", "argv"):
                continue
            _numeric_leaves(value, f"{prefix}.{key}" if prefix else str(key), out, limit)
    elif isinstance(data, list):
        if data and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in data) and len(data) <= 8:
            out.append((prefix, ", ".join(_fmt(v) for v in data)))
        else:
            for i, value in enumerate(data[:12]):
                _numeric_leaves(value, f"{prefix}[{i}]", out, limit)
    elif isinstance(data, (int, float)) and not isinstance(data, bool):
        out.append((prefix, _fmt(data)))
    return out


_BENCH_COLUMNS = [("scene", "scene"), ("resolution", "size"), ("backend", "backend"), ("precision", "precision"),
                  ("material", "material"), ("transfer", "transfer"), ("psnr", "PSNR dB"), ("ssim", "SSIM"),
                  ("fps", "FPS"), ("frame_ms", "ms/frame"), ("weight_bytes", "bytes"), ("ref_noise_psnr", "ref. noise dB")]  # fmt: skip


def _bench_table(data: dict) -> list[str]:
    records = data.get("records") or []
    cols = [(k, t) for k, t in _BENCH_COLUMNS if any(k in r for r in records)]
    lines = ["| " + " | ".join(t for _, t in cols) + " |", "|" + "---|" * len(cols)]
    for r in records:
        lines.append("| " + " | ".join(_fmt(r.get(k, "")).replace("|", "/") for k, _ in cols) + " |")
    return lines


_LINK = re.compile(r"(!?\[[^\]]*\])\(([^)\s]+)\)")


def _rebase_links(text: str) -> str:
    """Links of a ``docs/benchmarks/*.md`` table, made relative to ``docs/results/``."""

    def fix(m):
        target = m.group(2)
        if re.match(r"^[a-z]+:|^#|^/", target):
            return m.group(0)
        return f"{m.group(1)}(../benchmarks/{target})"

    return _LINK.sub(fix, text)


def _embedded_md(path: Path) -> list[str]:
    text = _rebase_links(path.read_text(encoding="utf-8"))
    out = []
    for line in text.splitlines():
        if line.startswith("#"):
            line = "#### " + line.lstrip("#").strip()  # its headings sit under the file's own
        out.append(line)
    return out


def _file_section(path: Path, history: dict) -> list[str]:
    data = json.loads(path.read_text(encoding="utf-8"))
    data = data if isinstance(data, dict) else {"values": data}
    prov = provenance_of(path.name, data, history)
    lines = [f"### {path.stem}\n", f"Recorded file: [`docs/benchmarks/{path.name}`](../benchmarks/{path.name})\n",
             f"- **Date:** {prov['date']}", f"- **Command:** `{prov['command']}`" if prov["command"] != "not recorded"
             else "- **Command:** not recorded", f"- **Machine:** {prov['machine']}", ""]  # fmt: skip
    md = path.with_suffix(".md")
    if md.is_file():
        lines += [f"Its table (`{md.name}`, written with it):\n", *_embedded_md(md), ""]
    elif data.get("tool") == "prt-bench" and data.get("records"):
        lines += _bench_table(data) + [""]
    else:
        leaves = _numeric_leaves(data)
        if leaves:
            lines += ["| figure | value |", "|---|---|", *(f"| `{k}` | {v} |" for k, v in leaves)]
            if len(leaves) >= 60:
                lines.append(f"| ... | more in the file |")
            lines.append("")
    return lines


def result_pages(root: Path) -> dict[Path, str]:
    """``docs/results/<page>.md`` for every page that has recorded files, and ``index.md``."""
    bench = root / "docs" / "benchmarks"
    history = _history(root)
    files = sorted(p for p in bench.glob("*.json") if not p.name.startswith("_"))
    by_page: dict[tuple, list[Path]] = {}
    for path in files:
        by_page.setdefault(_page_of(path.stem), []).append(path)
    out = {}
    header = "<!-- Generated by scripts/docs.py from docs/benchmarks/*.json; edit those, not this page. -->\n\n"
    index = [header, "# Results\n",
             "Every figure in these pages is read from a file recorded by the command that measured it "
             "(`docs/benchmarks/*.json`), shown with that file's date, command and machine. Figures "
             "measured on the project's 2-core CPU machines (no GPU; OpenGL from Mesa llvmpipe) are "
             "not what a GPU gives: see the GPU page. Where a file does not record its machine, the "
             "CPU is not known (the project's machines are Intel or AMD EPYC).\n",
             "| page | what | recorded files |", "|---|---|---|"]  # fmt: skip
    for page in [*PAGES, OTHER]:
        paths = by_page.get(page)
        if not paths:
            continue
        slug, title, what, _ = page
        lines = [header, f"# {title}\n", f"{what}\n"]
        for path in paths:
            lines += _file_section(path, history)
        out[root / "docs" / "results" / f"{slug}.md"] = "\n".join(lines).rstrip() + "\n"
        index.append(f"| [{title}]({slug}.md) | {what} | {len(paths)} |")
    out[root / "docs" / "results" / "index.md"] = "\n".join(index).rstrip() + "\n"
    return out


# -- the README's table -------------------------------------------------------------------------

START, END = "<!-- results:start (generated by scripts/docs.py) -->", "<!-- results:end -->"


def _load(root: Path, name: str) -> dict | None:
    path = root / "docs" / "benchmarks" / name
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _short_date(date: str) -> str:
    return date[:10] if re.match(r"^\d{4}-\d{2}-\d{2}", date) else date


def _short_machine(prov: dict) -> str:
    machine = prov["machine"]
    if machine.startswith("not recorded"):
        return "not recorded"
    return re.sub(r"\s+", " ", re.sub(r"\((R|TM)\)|\bProcessor\b|\bCPU\b", "", machine.split(",")[0])).strip()


def readme_rows(root: Path) -> list[tuple[str, str, str, str]]:
    """(figure, value, date and machine, source) rows of the README's results table."""
    history = _history(root)
    rows = []

    def add(name, figure, value):
        data = _load(root, name)
        if data is None or value is None:
            return
        prov = provenance_of(name, data, history)
        rows.append((figure, value(data) if callable(value) else value, f"{_short_date(prov['date'])}, {_short_machine(prov)}",
                     f"[{name}](docs/benchmarks/{name})"))

    def demo(d):
        rows_ = d.get("rows", {})
        first = next(iter(rows_.values()), None)
        if first is None:
            return None
        load = (d.get("provenance", {}).get("machine", {}) or {}).get("other_cpu_share") or 0.0
        busy = f"; other processes took {100 * load:.0f} % of the CPUs" if load >= 0.05 else ""
        return f"{first['fps']:.1f} FPS at {d.get('size', '?')}x{d.get('size', '?')} (ONNX backend, CPU{busy})"

    add("demo_fps.json", "`make demo` frame rate", demo)

    paper = _load(root, "paper.json")
    if paper:
        for mesh in ("bunny", "spot", "teapot", "daffodil"):
            def cell(d, mesh=mesh):
                recs = [r for r in d["records"] if r["material"] == "diffuse" and r["precision"] == "fp32" and r.get("interpolate") is None]
                ours = [r for r in recs if r["scene"] == f"{mesh}-right-sized" and r["backend"] == "onnx"]
                vert = [r for r in recs if r["scene"] == f"{mesh}-right-sized" and r["backend"] == "vertex"
                        and ours and r.get("transfer") == ours[0].get("transfer")]  # the same bounces
                if not ours or not vert:
                    return None
                return (f"{ours[0]['psnr']:.1f} dB ({ours[0]['weight_bytes'] / 1024:.0f} KiB) vs vertex PRT "
                        f"{vert[0]['psnr']:.1f} dB ({vert[0]['weight_bytes'] / 1024:.0f} KiB)")
            value = cell(paper)
            if value:
                add("paper.json", f"{mesh}: right-sized build vs per-vertex PRT, same bounces (diffuse PSNR, bytes)", value)
    def web_pixels(d):
        demo = d.get("same_pixels", {}).get("demo, manifest camera")
        return None if demo is None else f"{demo['psnr_db']:.1f} dB from the Python GLSL backend (demo, {demo['size']}x{demo['size']})"

    def web_payload(d):
        pay, first = d.get("payload", {}), {r["size"]: r for r in d.get("load", [])}
        if not pay:
            return None
        text = f"{pay['geometry_weights_code_bytes'] / 1e6:.2f} MB (geometry, weights, code)"
        if 512 in first:
            text += f"; first frame {first[512]['first_frame_ms'] / 1e3:.1f} s at 512x512 in software WebGL"
        return text

    def mitsuba(d):
        cells = []
        for scene, sizes in d.get("summary", {}).items():
            for size, m in sizes.items():
                cells.append(f"{scene.split('-')[0]} {m['psnr_db']:.1f} dB (joint noise {m['joint_noise_psnr_db']:.1f}), "
                             f"bias {100 * m['bias']:+.2f} %")
        return "; ".join(cells) or None

    def presets(d):
        cells = []
        for b in d.get("builds", []):
            t, rows = b["timing"], b.get("rows") or []
            own = next((r for r in rows if r.get("scene") == b.get("scene")), None)
            psnr = f", {own['psnr_db']:.1f} dB vs vertex PRT {own['vertex_psnr_db']:.1f} dB" if own else ""
            cells.append(f"{t['quality']} {t['wall_s'] / 60:.1f} min{psnr}")
        name = Path(d["builds"][0]["timing"]["mesh"]).name if d.get("builds") else "?"
        return f"{name} ({d['builds'][0]['timing']['vertices']:,} vertices): " + "; ".join(cells) if cells else None

    add("mitsuba_reference.json", "our reference against Mitsuba 3 (path traced, same scene)", mitsuba)
    def defaults(d):
        cells = {}
        for b in d.get("builds", []):
            for r in b.get("rows") or []:
                cell = cells.setdefault(r["mesh"], {"gains": [], "bytes": r["weight_bytes"] / r["vertex_bytes"], "equal": []})
                cell["gains"].append(f"{r['gain_db']:+.2f}")
                cell["equal"].append(f"{r['gain_equal_bytes_db']:+.2f}")
        return "; ".join(f"{Path(m).stem} {' / '.join(c['gains'])} dB at {c['bytes']:.2f}x its bytes "
                         f"({' / '.join(c['equal'])} dB at equal bytes)" for m, c in cells.items()) or None

    add("presets.json", "`prt-train --quality` build time on 2 cores, diffuse PSNR", presets)
    add("presets_bunny.json", "`prt-train --quality` build time on 2 cores, diffuse PSNR", presets)
    add("presets_spot.json", "`prt-train --quality` build time on 2 cores, diffuse PSNR", presets)
    add("defaults_unseen.json", "default build vs per-vertex PRT with the same bounces, unseen meshes (diffuse PSNR gain, own light / venice_sunset)",
        defaults)
    add("web.json", "`prt-web` page of the demo: same pixels", web_pixels)
    add("web.json", "`prt-web` page of the demo: payload, first frame", web_payload)

    def scenes(d):
        cells = []
        for s in d.get("scenes", []):
            groups = "; ".join(
                f"{g} {c['configurations'].get('onnx', {}).get('psnr_db')} dB (vertex PRT {c['configurations'].get('vertex', {}).get('psnr_db')}, "
                f"probes at equal bytes {next((v['psnr_db'] for k, v in c['configurations'].items() if k.startswith('probes equal')), '-')})"
                for g, c in s["groups"].items())  # fmt: skip
            cells.append(f"{s['name']} ({s['triangles']:,} triangles, {s['objects']} objects): build {s['timing']['wall_s'] / 60:.1f} min; {groups}")
        return "; ".join(cells) or None
    add("scenes_real.json", "real scenes at the defaults, diffuse PSNR from their own cameras (exposure matched)", scenes)
    add("scenes_real_copies.json", "the same on public copies of a house and an assembly (origin and sha1: docs/benchmarks/cameras/SOURCES.md)", scenes)
    add("scenes_real_clear.json", "the copies again, bounce lookups kept to their side of walls (and the reference's)", scenes)
    add("scenes_real_traced.json", "the house again, the first bounce traced at hits far from any clear sample", scenes)
    add("scenes_real_small_batches.json", "the house again, the standard preset's fits at 4,000 steps of 256 (were 1,000 of 4,096)", scenes)
    add("scenes_real_small_batches_as1.json", "the assembly again, the same fits", scenes)
    add("scenes_real_encode_once.json", "the house again, each fit's samples encoded once (12-13 % less time a step)", scenes)
    return rows


def readme_with_table(text: str, root: Path) -> str:
    """``text`` (the README) with the table between its markers regenerated (unchanged without markers)."""
    if START not in text or END not in text:
        return text
    rows = readme_rows(root)
    table = ["| figure | value | date, CPU | recorded in |", "|---|---|---|---|", *(f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows)]
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    return head + START + "\n" + "\n".join(table) + "\n" + END + tail


NAV_START = "  # results-nav:start (generated by scripts/docs.py from docs/benchmarks/*.json)"
NAV_END = "  # results-nav:end"


def mkdocs_with_nav(text: str, root: Path) -> str:
    """``mkdocs.yml`` with its Results section listing every results page there is (between markers)."""
    if NAV_START not in text or NAV_END not in text:
        return text
    pages = result_pages(root)
    lines = [NAV_START, "  - Results:", "      - results/index.md"]
    for slug, title, _, _ in [*PAGES, OTHER]:
        if root / "docs" / "results" / f"{slug}.md" in pages:
            lines.append(f"      - {title}: results/{slug}.md")
    head, rest = text.split(NAV_START, 1)
    _, tail = rest.split(NAV_END, 1)
    return head + "\n".join(lines) + "\n" + NAV_END + tail
