"""``python -m dax_tasks.bench`` runs :mod:`dax_tasks.tools.bench` (kept so the published
command keeps working; the benchmark lives in the tools subpackage)."""

from .tools.bench import main

if __name__ == "__main__":
    main()
