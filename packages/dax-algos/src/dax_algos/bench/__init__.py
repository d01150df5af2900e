"""The benchmark runner ``dax-bench`` and what it writes. The command (:mod:`.runner`), the
grid and its resume (:mod:`.grid`), the runs of a method on a task (:mod:`.execute`, also
what a Ray worker calls: :mod:`.backends`), ``results.csv`` (:mod:`.rows`, append-only
logs :mod:`.csvlog`), the output directory and ``run.json`` (:mod:`.rundir`), the reports
(:mod:`.summary`: tables and charts :mod:`.report`, the results page :mod:`.page`, episode
recordings and pictures :mod:`.episodes`, learning curves :mod:`.learning`) and trained
policy files (:mod:`.trained`, :mod:`.policy_io`). It imports the methods through their
protocol (:mod:`dax_algos.method`); no method imports it."""
