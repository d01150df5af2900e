"""Benchmark and demo scripts of dax-physics, and the timing helpers they (and the other
DaX packages' benchmarks) share.

* :mod:`.timing`: :func:`~.timing.median_time`, :func:`~.timing.peak_rss_mb`,
  :func:`~.timing.emit` (one JSON line per record);
* ``python -m dax_physics.tools.bench --help``: MPM and cloth benchmarks (JSON);
* ``python -m dax_physics.tools.demo --out demo_out``: the physics demo.

Nothing in the solvers imports this subpackage.
"""
