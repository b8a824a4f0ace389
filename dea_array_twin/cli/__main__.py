"""``python -m dea_array_twin.cli``: the ``dea-twin`` command."""

import sys

from .main import main

sys.exit(main())
