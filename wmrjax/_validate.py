"""Argument checks that run on concrete values before anything is traced or compiled.

Every check is skipped for tracers (values inside ``jit``/``vmap``/``grad``): there the
caller has already been validated at the outer entry point.
"""

from __future__ import annotations

import numpy as np
from jax import core


def is_concrete(x) -> bool:
    return not isinstance(x, core.Tracer)


def concrete(x):
    """``np.asarray(x)`` if ``x`` is concrete, else ``None``."""
    if isinstance(x, core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # pragma: no cover - exotic array types
        return None


def check_shape(name: str, x, shape: tuple, what: str = "") -> None:
    """Raise ``ValueError`` unless ``x`` has exactly ``shape``."""
    got = tuple(np.shape(x))
    if got != tuple(shape):
        extra = f" ({what})" if what else ""
        raise ValueError(f"{name} must have shape {tuple(shape)}{extra}, got shape {got}")


def check_finite(name: str, x) -> None:
    v = concrete(x)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {v!r}")


def check_positive(name: str, x) -> None:
    v = concrete(x)
    if v is None:
        return
    if not np.isrealobj(v) or not np.issubdtype(v.dtype, np.number) or not np.all(np.isfinite(v)) or not np.all(v > 0):
        raise ValueError(f"{name} must be real, finite and > 0, got {v!r}")


def check_int(name: str, x, minimum: int = 1) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {x!r}")
    return int(x)


def check_number(name: str, x, what: str = "real numbers") -> None:
    """ValueError for text, a boolean or a non-real value where numbers are meant, before any
    arithmetic turns it into a raw TypeError (``"0.01"``) or silently into 1.0 (``True`` for a
    step or a pole is a typo, not a number); traced values pass."""
    if isinstance(x, core.Tracer):
        return
    if isinstance(x, (str, bytes, bool, np.bool_)):
        raise ValueError(f"{name} must be {what}, got {type(x).__name__} {_short(x)}")
    try:
        kind = np.asarray(x).dtype.kind
    except (TypeError, ValueError):
        kind = "O"
    if kind not in "iuf":
        raise ValueError(f"{name} must be {what}, got {type(x).__name__} {_short(x)}")


def _short(x, limit: int = 60) -> str:
    """``repr(x)``, cut to ``limit`` characters (a message never quotes a value at length)."""
    r = repr(x)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def check_real(name: str, x) -> None:
    """ValueError for a complex (or non-numeric) array: its imaginary part would be dropped silently."""
    if hasattr(x, "dtype"):
        dt = np.dtype(x.dtype)
    else:
        try:  # nested lists: np.result_type would read them as a structured dtype
            dt = np.asarray(x).dtype
        except (TypeError, ValueError):
            dt = np.dtype(object)
    if dt.kind == "c":
        raise ValueError(f"{name} must be real, got a complex array of dtype {dt}")
    if dt.kind not in "biuf":
        raise ValueError(f"{name} must be a numeric array, got dtype {dt}")
