"""`flipviz bench`: the paper's Table III (and Table II) as many resumable, parallel runs."""

from flipviz.bench.config import BenchConfig
from flipviz.bench.runner import plan, run_bench

__all__ = ["BenchConfig", "run_bench", "plan"]
