"""Shared plumbing for the experiment entry points (not part of the library API)."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np


def enable_x64() -> None:
    """Experiments run in float64 (the library never flips this on import)."""
    import jax

    jax.config.update("jax_enable_x64", True)


def parser(description: str, default_out: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--out", type=Path, default=Path(default_out), help=f"output directory (default {default_out})")
    return p


def _atomic(path: Path, write) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return _jsonable(np.asarray(x).tolist())
    if isinstance(x, float) and not np.isfinite(x):
        return None if np.isnan(x) else ("inf" if x > 0 else "-inf")
    return x


def write_json(path: Path, obj) -> None:
    """Write JSON atomically (write to a temp file, then rename)."""
    data = json.dumps(_jsonable(obj), indent=2, sort_keys=False).encode()
    _atomic(path, lambda fh: fh.write(data + b"\n"))


def write_npz(path: Path, **arrays) -> None:
    """Write an ``.npz`` of plain numeric arrays atomically (no pickled objects)."""
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for k, v in arrays.items():
        if v.dtype == object:
            raise ValueError(f"refusing to save object array {k!r}: npz files here never hold pickles")
    _atomic(path, lambda fh: np.savez(fh, **arrays))


def save_figure(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    _atomic(path, lambda fh: fh.write(buf.getvalue()))


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
