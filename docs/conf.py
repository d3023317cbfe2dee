"""Sphinx configuration of the wmrjax documentation.

Build: ``make docs`` (warnings are errors; every tutorial executes). Sphinx + MyST-NB, as
JAX and optax do: the tutorials are MyST text notebooks (diff-friendly Markdown) executed
at build time, the API pages are generated from the Google-style docstrings by napoleon,
and MathJax is served from the build itself so that the pages render offline.
"""

import importlib.util
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# the tutorials' kernels run on the CPU with float64, like the tests
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_ENABLE_X64", "1")

from sphinx.util.parallel import make_chunks  # noqa: E402

import wmrjax  # noqa: E402

project = "wmrjax"
author = "the wmrjax developers"
copyright = "2026, the wmrjax developers"
release = wmrjax.__version__
version = release

extensions = ["myst_nb", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]

exclude_patterns = ["_build", "**.ipynb_checkpoints", "README.md"]
source_suffix = {".md": "myst-nb", ".rst": "restructuredtext"}
root_doc = "index"

# MyST: $...$ math, definition lists, heading anchors for in-page links
myst_enable_extensions = ["dollarmath", "amsmath", "deflist", "colon_fence"]
myst_heading_anchors = 3

# Tutorials execute at build time; their outputs are cached between builds (keyed by the
# cell sources), and an error in any cell fails the build.
nb_execution_mode = os.environ.get("WMRJAX_DOCS_EXECUTE", "cache")
nb_execution_cache_path = str(ROOT / "docs" / "_build" / ".jupyter_cache")
nb_execution_timeout = 600
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True

autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": False}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
# a class's fields are in its docstring: no second, undocumented "Parameters" list of them
autodoc_typehints_description_target = "documented"
autodoc_inherit_docstrings = False
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True

html_theme = "furo"
html_title = f"wmrjax {release}"
# MathJax from the build itself (the files of the sphinx-mathjax-offline package, copied into
# _static/mathjax), so that pages render their equations with no network
_MATHJAX = Path(importlib.util.find_spec("sphinx-mathjax-offline").origin).parent / "static"
html_static_path = [str(_MATHJAX)]
mathjax_path = "mathjax/tex-chtml.js"
html_show_sourcelink = False


def _skip_namedtuple_aliases(app, what, name, obj, skip, options):
    """A NamedTuple's fields are documented in its class docstring; skip the generated
    "Alias for field number N" entries, and a dataclass's annotated fields (its docstring's
    ``Attributes``: listed again, they would be a second target of every field name)."""
    if repr(obj) in ("INSTANCE_ATTR", "UNINITIALIZED_ATTR"):  # autodoc's sentinels (private in Sphinx 9)
        return True
    doc = getattr(obj, "__doc__", None) or ""
    if isinstance(obj, property) or type(obj).__name__ == "_tuplegetter":
        if doc.startswith("Alias for field number"):
            return True
    return None


def _spread_notebooks(app, env, docnames):
    """Sphinx reads documents in parallel by consecutive chunks of the (sorted) list, so the
    tutorials, which execute and are neighbours by name, would run one after the other in one
    process: deal them out over the chunks read first, lightest pages after."""
    nproc = max(1, app.parallel)
    chunks = make_chunks(list(docnames), nproc)
    if nproc == 1 or len(chunks) < 2:
        return
    notebooks = [d for d in docnames if d.startswith("tutorials/") and d != "tutorials/index"]
    pages = [d for d in docnames if d not in notebooks]
    size = len(chunks[0])
    dealt = [notebooks[i::nproc] for i in range(nproc)]
    order = []
    for i in range(len(chunks)):
        mine = dealt[i] if i < nproc else []
        while pages and len(mine) < size:
            mine.append(pages.pop(0))
        order += mine
    docnames[:] = order + pages


def _create_execution_cache(app):
    """Create the notebooks' execution cache before the parallel readers start, which would
    otherwise race to create its database."""
    from jupyter_cache import get_cache

    get_cache(nb_execution_cache_path).list_cache_records()


def setup(app):
    app.connect("builder-inited", _create_execution_cache)
    app.connect("autodoc-skip-member", _skip_namedtuple_aliases)
    app.connect("env-before-read-docs", _spread_notebooks)
