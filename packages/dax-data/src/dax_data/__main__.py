"""``python -m dax_data`` runs the ``dax-data`` command line."""

import sys

from .cli import main

sys.exit(main())
