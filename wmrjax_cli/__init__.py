"""wmrjax_cli: the layer between the library and the command lines (installed with the ``cli``
extra: ``pip install "wmrjax[cli]"``).

* :mod:`wmrjax_cli.options` -- the shared parser (``--out``, the compilation cache,
  ``--verbose``), option types that refuse bad values at parse time, the output directory
  prepared before any work, a heartbeat, and the exit statuses (2: a bad option, 1: an
  error of the work).
* :mod:`wmrjax_cli.files` -- atomic JSON/NPZ/PNG/Parquet writers, JSON checkpoints and one
  writer per output directory.

It imports the library (:mod:`wmrjax`) and never the command lines (``tuning``,
``experiments``); the library never imports it.
"""

import importlib.util as _importlib_util
import sys as _sys

# The command lines write figures and tables at the end of their work: without the extra they
# would compute for minutes and then fail on an import. Say so before anything runs.
_CLI_EXTRA = ("matplotlib", "pyarrow", "cmaes", "optuna")
_missing = [
    name
    for name in _CLI_EXTRA
    if (_sys.modules[name] is None if name in _sys.modules else _importlib_util.find_spec(name) is None)
]
if _missing:
    raise ImportError(
        f"the wmrjax command lines need {', '.join(_missing)}: install them with "
        'pip install "wmrjax[cli]" (the library alone, wmrjax, needs only jax, numpy and optax)'
    )
