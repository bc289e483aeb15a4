"""Repository tooling beside the installed pipeline: benchmarks (bench_*.py), the results page (write_results.py),
the learning curve, strips, ACT training and probing, merging adapters. Each runs as `python scripts/<name>.py`
from the checkout root; every pipeline step is a console script instead (labrobfail-*, pyproject.toml).
"""
