"""What the command lines share beyond :mod:`wmrjax.cli.options`: float64, writing results and
figures (atomically, through :mod:`wmrjax._files`) and quantiles for their summaries."""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

from wmrjax import _files as files
from wmrjax._math import quantiles  # noqa: F401 -- the summaries' statistics, re-exported
from wmrjax.cli import options


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    return files.headless_pyplot()


def write_json(path: Path, obj) -> None:
    """Write JSON atomically (:func:`wmrjax._files.write_json`)."""
    files.write_json(path, obj)


def write_npz(path: Path, **arrays) -> None:
    """Write a pickle-free ``.npz`` atomically (:func:`wmrjax._files.write_npz`)."""
    files.write_npz(path, **arrays)


def enable_x64() -> None:
    """The command lines run in float64 (the library never flips this on import)."""
    jax.config.update("jax_enable_x64", True)


def parser(description: str, default_out: str | None, compile_cache: bool = True) -> argparse.ArgumentParser:
    """A command's parser (:func:`wmrjax.cli.options.parser`: defaults shown, ``--out``, the
    persistent compilation cache on unless ``compile_cache`` is False)."""
    return options.parser(description, default_out, compile_cache)


def save_figure(fig, path: Path) -> None:
    """Write a figure as PNG (atomically)."""
    files.write_png(fig, path)
