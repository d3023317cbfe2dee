r"""XLA:CPU settings for this library's time loops, applied once, before JAX starts its backend.

A rollout is a ``lax.scan`` of thousands of small steps. XLA:CPU runs a loop's body as a
sequence of compiled kernels ("thunks"), dispatched one after the other at every step; when a
batch is small (the certification's confirmations: 16 runs of 10 000 steps; a gradient stage
of the falsifier; a tuner's few scenarios) that dispatch, not the arithmetic, sets the time. XLA
compiles a while loop whose memory traffic is below its option
``xla_cpu_small_while_loop_byte_threshold`` (1 kB by default) into a single kernel instead.
:func:`configure_cpu` raises that threshold to :data:`SMALL_LOOP_BYTES`, so that every time
loop is compiled whole: small batches run several times faster, large ones at the same speed
(measurements: docs/benchmarks.md). The kernels differ, so results agree with the default
setting to rounding, not to the bit.

XLA reads ``XLA_FLAGS`` once, when JAX starts its backend (the first array or computation):
call :func:`configure_cpu` first thing in a script, or put :func:`cpu_flags`'s string in the
environment. The command lines of this project call it themselves; the library never changes
the environment on import.
"""

from __future__ import annotations

import os
import warnings

# the small-while-loop threshold the command lines set [bytes accessed by a loop]: above any
# loop of this library's programs, so that every one is compiled into one kernel
SMALL_LOOP_BYTES = 1_000_000_000
SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options="
_DEVICES = "--xla_force_host_platform_device_count="


def cpu_flags(xla_flags: str = "", devices: int | None = None) -> str:
    """``xla_flags`` (an ``XLA_FLAGS`` string) with this library's CPU settings added.

    A small-loop threshold already in ``xla_flags`` is kept (``...threshold=0`` turns the
    single-kernel loops off); a device count there is replaced by ``devices`` when it is given.

    Args:
      xla_flags: the flags to extend (typically ``os.environ.get("XLA_FLAGS", "")``).
      devices: host devices JAX should expose (``--xla_force_host_platform_device_count``,
        one per core for :func:`wmrjax.batch_map`), or None to leave the count alone.

    Returns:
      The extended flags, space-separated.
    """
    if devices is not None and (isinstance(devices, bool) or not isinstance(devices, int) or devices < 1):
        raise ValueError(f"devices must be an integer >= 1 or None, got {devices!r}")
    if not isinstance(xla_flags, str):
        raise ValueError(f"xla_flags must be a string of XLA flags, got {type(xla_flags).__name__}")
    tokens = xla_flags.split()
    if SMALL_LOOP_OPTION not in xla_flags:
        extra = [i for i, tok in enumerate(tokens) if tok.startswith(_EXTRA)]
        option = f"{SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
        if extra:  # one map of backend options: the last one given counts, so extend it
            tokens[extra[-1]] = tokens[extra[-1]].rstrip(",")
            tokens[extra[-1]] += ("," if tokens[extra[-1]] != _EXTRA else "") + option
        else:
            tokens.append(_EXTRA + option)
    if devices is not None:  # the count asked for, whatever the environment held
        tokens = [tok for tok in tokens if not tok.startswith(_DEVICES)] + [f"{_DEVICES}{devices}"]
    return " ".join(tokens)


def configure_cpu(devices: int | None = None) -> bool:
    """Put :func:`cpu_flags` into ``os.environ["XLA_FLAGS"]``, for the JAX backend this process
    starts next (and for the processes it starts: they inherit the environment).

    Args:
      devices: host devices to expose (see :func:`cpu_flags`), or None.

    Returns:
      True if the single-kernel loops apply in this process: JAX has not started its backend
      yet, or the environment held the setting already when this was called (the backend is
      then taken to have read it). False, with a ``RuntimeWarning``, if the backend already runs
      and the environment did not hold it: XLA has read its flags, and this process's loops
      keep the default (the same results to rounding, slower for small batches).
    """
    current = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = cpu_flags(current, devices)
    if SMALL_LOOP_OPTION in current:
        return True
    from jax._src import xla_bridge  # no public test of whether the backend has started

    if xla_bridge.backends_are_initialized():
        warnings.warn(
            "wmrjax.configure_cpu: JAX's backend has already started and read XLA_FLAGS; call it before "
            "the first JAX computation (or set XLA_FLAGS before starting Python)",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    return True
