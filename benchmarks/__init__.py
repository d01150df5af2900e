"""Benchmarks, studies, the validation suite and the demos of DaX: what measures the
libraries, kept out of them. Run each from the repository root as a module, e.g.
``python -m benchmarks.tasks --json`` or ``python -m benchmarks.validate --out DIR``; see
``benchmarks/README.md`` for the list. They print JSON, and write their result files with
:func:`benchmarks._report.write_report`."""
