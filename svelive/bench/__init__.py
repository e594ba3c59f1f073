"""Speed against accuracy: the benchmark runner, the sequential-bracketing reference and the stability sweeps.

``svelive bench`` (svelive/cli/bench.py) runs :func:`svelive.bench.runner.run_benchmark`;
the chart needs matplotlib, the optional extra ``bench`` (``pip install .[bench]``).
"""
