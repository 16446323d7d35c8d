# The two commands a newcomer needs (see README.md); both install what is missing first.
.PHONY: demo test bench install docs web

install:
	@bash scripts/bootstrap.sh

demo: install
	.venv/bin/prt-runtime --headless --frames 30 --out demo_out

# The demo scene as a static web page (WebGL2, the viewer's GPU): docs/guides/web.md.
web: install
	.venv/bin/prt-web runtime/data/demo -o web_demo

test: install
	.venv/bin/python -m pytest -q

bench: install
	.venv/bin/python studies/precompute_bench.py --json docs/benchmarks/precompute_bunny.json
	.venv/bin/python studies/train_bench.py --json docs/benchmarks/train_bunny.json
	.venv/bin/python studies/runtime_bench.py --json docs/benchmarks/runtime.json
	RAY_USAGE_STATS_ENABLED=0 .venv/bin/python studies/cluster_bench.py --json docs/benchmarks/cluster.json

# The documentation site: regenerate the generated pages (CLI, scene.json, results, the README's
# table), then a strict build into site/ (broken links, missing or unlisted pages fail it).
docs: install
	.venv/bin/python scripts/docs.py
	NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict
