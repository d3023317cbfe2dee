"""What runs inside every probe case's process (this directory is on the case's ``PYTHONPATH``,
after the tree under test): a spy on JAX's time loops and, for Python cases, the snippet runner.

Standard library only: it is loaded before the tree's code and must work with any tree.

The spy wraps ``jax.lax.scan`` and ``jax.lax.map`` when ``jax.lax`` is first imported and appends
one line to ``$PROBE_EVENTS`` the first time a process traces one (every rollout, optimisation and
batch of wmrjax runs under one: a trace means the work has started). A snippet calls ``arm()``
just before the call under test; the oracle then counts only the traces after the last arm.

A Python case is run as ``python -c "import probe_hook; probe_hook.run('case.py')"``: the snippet
is executed with a few names predefined (``emit``, ``arm``, and with ``prelude``: JAX in float64
with the run's compilation cache, ``np``, ``jnp``, ``w``, ``R``, ``C``, ``loop61`` and
``circle_samples``). It reports through lines
on stdout: ``PROBE_RESULT {json}`` (``emit``), ``PROBE_WARN {json}`` (every warning) and, when it
raises, ``PROBE_EXC {json}`` (type, message, whether it is a ValueError) before exiting with 1.
"""

import importlib.abc
import importlib.util
import json
import os
import sys
import time
import traceback
import warnings

_START = time.monotonic()
_traced = False


def _event(kind: str) -> None:
    path = os.environ.get("PROBE_EVENTS")
    if not path:
        return
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps({"event": kind, "pid": os.getpid(), "t": round(time.monotonic() - _START, 3)}) + "\n")


def arm() -> None:
    """Mark the start of the call under test: only time loops traced after it count as late."""
    global _traced
    _traced = False
    _event("arm")


def _spy(fn):
    def wrapped(*args, **kwargs):
        global _traced
        if not _traced:
            _traced = True
            _event("trace")
        return fn(*args, **kwargs)

    wrapped.__wrapped__ = fn
    return wrapped


class _LaxFinder(importlib.abc.MetaPathFinder):
    """Wraps jax.lax's scan and map right after jax.lax is imported, then steps aside."""

    def find_spec(self, name, path=None, target=None):
        """jax.lax's own spec, its loader wrapped; None for every other module."""
        if name != "jax.lax":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            for attr in ("scan", "map"):
                if hasattr(module, attr):
                    setattr(module, attr, _spy(getattr(module, attr)))

        spec.loader.exec_module = exec_module
        return spec


def install() -> None:
    """Install the spy (once, and only in a probe case: ``$PROBE_EVENTS`` set)."""
    if os.environ.get("PROBE_EVENTS") and "jax.lax" not in sys.modules:
        if not any(isinstance(f, _LaxFinder) for f in sys.meta_path):
            sys.meta_path.insert(0, _LaxFinder())


def emit(**values) -> None:
    """Report values to the oracle (one JSON line; NumPy scalars and arrays are converted)."""
    print("PROBE_RESULT " + json.dumps(values, default=_plain), flush=True)


def _plain(x):
    if hasattr(x, "tolist"):
        return x.tolist()
    return str(x)


def _show(message, category, filename, lineno, file=None, line=None):
    print("PROBE_WARN " + json.dumps({"category": category.__name__, "message": str(message)[:2000]}), flush=True)
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _prelude(scope: dict, x64: bool) -> None:
    import jax

    jax.config.update("jax_enable_x64", x64)
    cache = os.environ.get("PROBE_XLA_CACHE")
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w
    from wmrjax import certify as C
    from wmrjax import references as R

    scope.update(jax=jax, jnp=jnp, np=np, w=w, R=R, C=C)

    def loop61(poles=1.0):
        """The paper's section 6.1 loop: (2,0), e = 0, reference (62): ``(ctrl, params, z0)``."""
        ctrl = w.dynamic_linearization("(2,0)", "velocity")
        params = ctrl.params(R.paper_62(), poles=poles, geometry=w.Geometry(e=0.0))
        return ctrl, params, ctrl.reference_state(0.0, params)

    def circle_samples(t0=0.0, t1=4.0, n=81):
        """Samples of the circle of radius 2 m at 0.5 rad/s on [t0, t1]: ``(ts, xy, circle)``."""
        circ = R.circle(radius=2.0, omega=0.5)
        ts = np.linspace(t0, t1, n)
        return ts, np.asarray(jax.vmap(circ.position)(jnp.asarray(ts))), circ

    scope.update(loop61=loop61, circle_samples=circle_samples)


def run(path: str) -> None:
    """Execute the snippet in ``path`` (see the module docstring); exit 1 with PROBE_EXC if it raises."""
    warnings.simplefilter("always")
    warnings.showwarning = _show
    scope = {"__name__": "__probe__", "emit": emit, "arm": arm}
    mode = os.environ.get("PROBE_PRELUDE", "x64")
    try:
        if mode != "none":
            _prelude(scope, x64=mode == "x64")
        with open(path, encoding="utf-8") as f:
            code = compile(f.read(), path, "exec")
        exec(code, scope)
    except BaseException as exc:  # noqa: BLE001 - the outcome is what the user would see
        if isinstance(exc, SystemExit) and exc.code in (0, None):
            raise
        traceback.print_exc()
        record = {
            "type": type(exc).__name__,
            "module": type(exc).__module__,
            "value_error": isinstance(exc, ValueError),
            "message": str(exc)[:4000],
            "traced": _traced,
        }
        print("PROBE_EXC " + json.dumps(record), flush=True)
        sys.stdout.flush()
        os._exit(1)
