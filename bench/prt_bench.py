"""The backend benchmark (``prt-bench``), runnable from a checkout: python bench/prt_bench.py --help."""

import sys

from prt.train.benchmark import main

if __name__ == "__main__":
    sys.exit(main())
