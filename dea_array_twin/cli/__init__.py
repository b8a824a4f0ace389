"""The ``dea-twin`` command: one module per sub-command over the layers below.

:mod:`.main` holds the parser, ``curve``, ``solve``, ``run``, ``demo`` and
``bag-recover``; :mod:`.study`, :mod:`.calibrate`, :mod:`.replay`, :mod:`.plot` and :mod:`.rom` the
options, output files and exit codes of the tools of those names; :mod:`.argtypes` the
argument types they share.  The top layer: it may import everything, nothing imports it.
"""

from .main import main

__all__ = ["main"]
