"""The shared command-line layer: the persistent compilation cache (in subprocesses: it is global JAX
configuration, which the library itself never touches)."""

import subprocess
import sys

SCRIPT = """
import sys, jax
from wmrjax import cli
p = cli.parser("x", None)
a = p.parse_args(sys.argv[1:])
print(cli.use_compilation_cache(a), jax.config.jax_compilation_cache_dir,
      jax.config.jax_persistent_cache_min_compile_time_secs)
"""


def _run(*argv):
    return subprocess.run([sys.executable, "-c", SCRIPT, *argv], capture_output=True, text=True, check=True).stdout.split()


def test_compilation_cache_on_by_default_off_on_request(tmp_path):
    d = tmp_path / "cache"
    assert _run("--compile-cache", str(d)) == [str(d), str(d), "0.0"]
    assert d.is_dir()
    assert _run("--compile-cache", str(d), "--no-compile-cache")[:2] == ["None", "None"]


def test_library_import_leaves_the_cache_alone():
    out = subprocess.run([sys.executable, "-c", "import jax, wmrjax; print(jax.config.jax_compilation_cache_dir)"],
                         capture_output=True, text=True, check=True).stdout.strip()
    assert out == "None"
