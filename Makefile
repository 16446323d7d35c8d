# The two commands a newcomer needs (see README.md); both install what is missing first.
.PHONY: demo test bench install

install:
	@bash scripts/bootstrap.sh

demo: install
	.venv/bin/prt-precompute creature -o demo_out --samples 20000 --rays 256 --segments 4

test: install
	.venv/bin/python -m pytest -q

bench: install
	.venv/bin/python bench/precompute_bench.py
