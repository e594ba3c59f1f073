"""Speed against accuracy: the benchmark runner, the sequential-bracketing reference and the stability sweeps.

``svelive bench`` (commands.py) runs :func:`svelive.bench.runner.run_benchmark`;
the chart needs matplotlib, the optional extra ``bench`` (``pip install .[bench]``).
"""
