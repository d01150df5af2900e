"""Benchmark scripts of dax-tasks: ``python -m dax_tasks.tools.bench --json`` times every
task (reset, step, step + gradient, compile) at batch 1 and 8. The timing helpers are
dax-physics' (:mod:`dax_physics.tools.timing`)."""
