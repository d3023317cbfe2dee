"""What every command line of this project shares at parse time: argument types that refuse
bad values, the parser (``--out``, the compilation cache, ``--verbose``) and :func:`fail`.

The ``wmrjax`` jobs and the repository's scripts (``python -m paper.*``, ``benchmarks.*``)
build their parsers with :func:`parser` and declare each option with one of the types below,
so a bad value stops the program in milliseconds with ``argument --name: ...`` naming the
option and the expected form, before JAX compiles anything. The problem's options are
:mod:`wmrjax.cli.problem_args`; the machine set-up :mod:`wmrjax.cli.machine`; the work and how
it ends :mod:`wmrjax.cli.running`.

Exit statuses: 2 with the usage text for a bad option (argparse's own errors and the checks
made with :func:`fail` before the work starts); 1 for an error of the work itself (a
``ValueError`` raised by it, see :func:`wmrjax.cli.running.work`): ``PROG: error: MESSAGE``
without the usage, its traceback shown with ``--verbose``.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

# --- argument types ------------------------------------------------------------------------------


def _number(text: str, kind=float):
    try:
        v = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(
            f"expected {'an integer' if kind is int else 'a number'}, got {text!r}"
        ) from None
    if kind is float and not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return v


def finite(text: str) -> float:
    """A finite real number."""
    return _number(text)


def positive(text: str) -> float:
    """A finite number > 0."""
    v = _number(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return v


def nonnegative(text: str) -> float:
    """A finite number >= 0."""
    v = _number(text)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return v


def limit(text: str) -> float:
    """An actuator limit: a number > 0 or ``inf`` (no limit)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0 or inf, got {text!r}") from None
    if not v > 0:  # NaN, 0 and negative limits are refused
        raise argparse.ArgumentTypeError(f"must be > 0 (or inf: no limit), got {text!r}")
    return v


def fraction(text: str) -> float:
    """A number in [0, 1)."""
    v = _number(text)
    if not 0 <= v < 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return v


def _integer(minimum: int, maximum: int | None = None, what: str = ""):
    """An argparse type: an integer in [minimum, maximum)."""
    bound = f"in [{minimum}, {maximum})" if maximum is not None else f">= {minimum}"

    def parse(text: str) -> int:
        v = _number(text, int)
        if v < minimum or (maximum is not None and v >= maximum):
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {text!r}")
        return v

    parse.__name__ = what or f"integer {bound}"
    parse.__doc__ = f"{what.capitalize() or 'An integer'}: an integer {bound}."
    return parse


count = _integer(1, what="count")  # runs, steps, samples
nonnegative_int = _integer(0, what="nonnegative integer")
seed = _integer(0, 2**32, what="seed")  # a PRNG seed
grid_size = _integer(2, what="grid size")  # points per axis of a grid


# --- the parser ------------------------------------------------------------------------------------


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help text with each option's default appended."""


def default_cache_dir() -> Path:
    """Where compiled programs are kept between runs: ``$XDG_CACHE_HOME/wmrjax/xla`` (``~/.cache/...``)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "wmrjax" / "xla"


FRESH_HELP = (
    "start over in --out: another job's results there are removed (only the files it recorded writing), "
    "and a resumable job's own earlier progress (a sweep's blocks, the tuner's checkpoint) is discarded"
)


def parser(description: str, default_out: str | None, compile_cache: bool = True) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` whose help shows defaults, with ``--out`` and ``--fresh`` when
    ``default_out`` is given, the persistent compilation cache options (see
    :func:`use_compilation_cache`) and ``--verbose`` (see :func:`work`)."""
    p = argparse.ArgumentParser(description=description, formatter_class=_Formatter)
    if default_out is not None:
        p.add_argument("--out", type=Path, default=Path(default_out), help="output directory (created if missing)")
        p.add_argument("--fresh", action="store_true", help=FRESH_HELP)
    p.add_argument(
        "--compile-cache",
        type=Path,
        default=default_cache_dir() if compile_cache else None,
        help="directory of JAX's persistent compilation cache: a second run reuses the compiled programs "
        "of the first (turn it off with --no-compile-cache)",
    )
    p.add_argument("--no-compile-cache", action="store_true", help="do not read or write the compilation cache")
    p.add_argument(
        "--verbose",
        action="store_true",
        help="when the work fails, print the full traceback of its error (not only its message)",
    )
    return p


def fail(p: argparse.ArgumentParser, message: str):
    """Exit like argparse does for a bad argument (status 2, usage and message on stderr): for
    checks of the options made before the work starts, not for errors of the work (:func:`work`)."""
    p.error(message)


# --- progress --------------------------------------------------------------------------------------
