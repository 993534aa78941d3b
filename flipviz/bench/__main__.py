"""`python -m flipviz.bench ...`: the same as `flipviz bench ...`."""

import sys

import tyro

from flipviz.bench import BenchConfig, run_bench
from flipviz.data.dataset import DatasetError

if __name__ == "__main__":
    cfg = tyro.cli(BenchConfig)
    try:
        print(f"results: {run_bench(cfg)}")
    except (DatasetError, ValueError) as e:
        print(f"flipviz: error: {e}".splitlines()[0], file=sys.stderr)
        sys.exit(2)
