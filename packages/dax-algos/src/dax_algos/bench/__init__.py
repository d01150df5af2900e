"""The benchmark runner ``dax-bench`` (:mod:`.runner`) and what it writes: results rows and
tables (:mod:`.report`), the results page (:mod:`.page`), episode recordings and pictures
(:mod:`.episodes`), learning curves (:mod:`.learning`), trained policy files
(:mod:`.trained`, :mod:`.policy_io`), append-only logs (:mod:`.csvlog`) and the Ray backend
(:mod:`.backends`). It imports the methods; no method imports it."""
