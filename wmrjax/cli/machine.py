"""What a job sets up on the machine before its work: JAX's host devices and CPU options
(before JAX starts its backend), the persistent compilation cache, and a horizon and batch
checked against the memory available."""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import jax

from wmrjax import resources, xla_cpu
from wmrjax.cli.options import fail


def enable_x64() -> None:
    """The jobs run in float64 (the library never flips this on import)."""
    jax.config.update("jax_enable_x64", True)


def configure_xla(devices: int | None = None) -> None:
    """This project's XLA:CPU settings for the process (:func:`wmrjax.configure_cpu`: every time
    loop compiled into one kernel; ``devices`` host devices, one per core, if given). Call it
    right after parsing, before any JAX work: XLA reads its flags when JAX's backend starts
    (called in-process after that, e.g. from a test, it only sets the environment its workers get)."""
    with warnings.catch_warnings():
        # a command line called from Python after JAX started: its loops keep the caller's setting
        warnings.simplefilter("ignore", RuntimeWarning)
        xla_cpu.configure_cpu(devices)


def use_compilation_cache(args) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``args.compile_cache`` (unless
    ``--no-compile-cache``): every program is stored there (the small ones too: a tuning run
    compiles about 100 small programs) and loaded by later runs of any
    command line. Call it after parsing, before any JAX work; the
    library never does this on import. Returns the directory, or None when off."""
    path = None if args.no_compile_cache else args.compile_cache
    if path is None:
        return None

    path = Path(path).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(
            f"note: compilation cache {path} unavailable ({exc.strerror or exc}); compiling from scratch",
            file=sys.stderr,
        )
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


# more RK4 steps than this in one run is not a horizon but an overflow of t_final / dt (a run of
# 1e12 steps would take days at the fastest rate measured)
MAX_STEPS = 1e12


def check_horizon(
    p,
    *,
    t_final: float,
    dt: float,
    batch: int = 1,
    n_state: int = 4,
    saved_every: int = 1,
    t_name: str = "--t-final",
    dt_name: str = "--dt",
    fix: str | None = None,
) -> int:
    """Steps of a run of ``t_final`` in steps of ``dt``; exits if the step exceeds the horizon,
    the horizon is not a whole number of steps (to 1e-6), or the saved samples of ``batch``
    runs would not fit in the memory available now (:mod:`wmrjax.resources`; ``fix``: what the
    message tells the user to change, by default the step or the horizon)."""
    if dt > t_final:
        fail(p, f"{dt_name} = {dt} s is longer than the horizon {t_name} = {t_final} s")
    steps = t_final / dt
    if not math.isfinite(steps) or steps > MAX_STEPS:  # t_final = 1e308 or dt = 1e-300: no run of that length
        fail(
            p,
            f"{t_name} / {dt_name} = {t_final} s / {dt} s is {steps:.3g} steps, more than {MAX_STEPS:.0e}: shorten "
            f"{t_name} or raise {dt_name}",
        )
    n = int(round(steps))
    if abs(steps - n) > 1e-6 * max(1.0, steps):
        fail(p, f"{t_name} = {t_final} s is not a whole number of steps of {dt_name} = {dt} s ({steps:.6g} steps)")
    # the samples of the batch; the reference check's memory is simulate's own check
    est = resources.Estimate(resources.samples_bytes(n // saved_every + 1, n_state, 8, batch), 0.0)
    try:
        resources.check_fits(
            est, f"{t_name} / {dt_name} = {n} steps for {batch} runs", fix or f"raise {dt_name} or shorten {t_name}"
        )
    except ValueError as err:
        fail(p, str(err))
    return n
