"""wmrjax.xla_cpu: the XLA_FLAGS string it builds, that the setting reaches XLA (a time loop
compiled into one kernel), that it is refused once JAX's backend runs, that results agree with
XLA's default to rounding, and that every command line's ``main`` calls it (a text check: that
the call comes before JAX starts is each main's order, read in review)."""

import ast
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import wmrjax as w
from wmrjax import xla_cpu

ROOT = Path(__file__).resolve().parent.parent
OPTION = f"xla_cpu_small_while_loop_byte_threshold={xla_cpu.SMALL_LOOP_BYTES}"


def test_cpu_flags_adds_the_option_and_keeps_what_is_given():
    assert w.cpu_flags("") == f"--xla_backend_extra_options={OPTION}"
    assert w.cpu_flags("", devices=2) == (
        f"--xla_backend_extra_options={OPTION} --xla_force_host_platform_device_count=2"
    )
    # another flag kept in place; an existing map of backend options extended, not replaced (the
    # last map given is the one XLA keeps)
    assert w.cpu_flags("--xla_backend_optimization_level=0") == (
        f"--xla_backend_optimization_level=0 --xla_backend_extra_options={OPTION}"
    )
    assert w.cpu_flags("--xla_backend_extra_options=a=1") == f"--xla_backend_extra_options=a=1,{OPTION}"
    # the user's own threshold and device count win
    # the user's own threshold wins; a device count given replaces the environment's
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=0"
    assert w.cpu_flags(mine + " --xla_force_host_platform_device_count=4", devices=2) == (
        mine + " --xla_force_host_platform_device_count=2"
    )
    assert w.cpu_flags(mine + " --xla_force_host_platform_device_count=4") == (
        mine + " --xla_force_host_platform_device_count=4"
    )
    # a trailing comma of the user's map is not doubled
    assert w.cpu_flags("--xla_backend_extra_options=a=1,") == f"--xla_backend_extra_options=a=1,{OPTION}"
    # idempotent
    once = w.cpu_flags("--xla_dump_to=/tmp/x", devices=3)
    assert w.cpu_flags(once, devices=3) == once


@pytest.mark.parametrize("devices", [0, -1, True, 2.0, "2"])
def test_cpu_flags_refuses_a_bad_device_count(devices):
    with pytest.raises(ValueError, match="devices must be an integer >= 1"):
        w.cpu_flags("", devices=devices)


def test_cpu_flags_refuses_flags_that_are_not_a_string():
    with pytest.raises(ValueError, match="xla_flags must be a string"):
        w.cpu_flags(None)


def _python(code: str, xla_flags: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    run = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout


# a loop whose carry (400 float64, 3.2 kB) is above XLA's default threshold (1 kB): one kernel only
# with the setting; the compiled module marks such a loop's call "xla_cpu_small_call"
_LOOP = """
import jax, jax.numpy as jnp
def f(x):
    return jax.lax.scan(lambda c, _: (jnp.sin(c) * 0.5 + c * c, None), x, None, length=50)[0]
text = jax.jit(f).lower(jnp.ones(400)).compile().as_text()
"""


def test_the_setting_reaches_xla_only_before_the_backend_starts():
    before = _python(
        "import wmrjax\nprint(wmrjax.configure_cpu())" + _LOOP + "print('xla_cpu_small_call' in text)", xla_flags=""
    )
    assert before.split() == ["True", "True"]
    # without it, the same loop runs as thunks
    default = _python(_LOOP + "print('xla_cpu_small_call' in text)", xla_flags="")
    assert default.split() == ["False"]
    late = _python(
        textwrap.dedent("""
        import warnings, jax.numpy as jnp, wmrjax
        jnp.ones(2)  # the backend starts here
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ok = wmrjax.configure_cpu()
        print(ok, [str(c.message)[:60] for c in caught if c.category is RuntimeWarning])
        """)
        + _LOOP
        + "print('xla_cpu_small_call' in text)",
        xla_flags="",
    )
    first = late.splitlines()[0]
    assert first.startswith("False [") and "wmrjax.configure_cpu: JAX's backend has already started" in first
    assert late.splitlines()[1] == "False"


_ROLLOUT = """
import jax, numpy as np, wmrjax as w
from wmrjax import references as R
jax.config.update("jax_enable_x64", True)
c = w.dynamic_linearization("(2,0)")
p = c.params(R.paper_62(), poles=1.0)
z0 = c.reference_state(0.0, p) + np.linspace(-0.4, 0.4, 4)[:, None] * np.array([1.0, -1.0, 0.5, 0.0])
run = jax.jit(jax.vmap(lambda z: w.simulate(c, z, p, dt=0.01, n_steps=300, save_every=30).state))
states = np.asarray(run(z0)).ravel()
"""


def test_results_agree_with_the_default_setting_to_rounding():
    """The section 6.1 rollout (B = 4, 300 steps) in this session (the setting on, conftest) against
    a process with XLA's default loops: its flags without the setting."""
    flags = os.environ["XLA_FLAGS"]
    assert OPTION in flags
    here = {}
    exec(_ROLLOUT, here)
    default_flags = flags.replace(f"--xla_backend_extra_options={OPTION}", "")
    assert xla_cpu.SMALL_LOOP_OPTION not in default_flags, default_flags
    default = np.array(ast.literal_eval(_python(_ROLLOUT + "print(repr(states.tolist()))", default_flags).strip()))
    np.testing.assert_allclose(here["states"], default, rtol=1e-12, atol=1e-12)


def _mains():
    """Every command line's module (a ``main`` function), as source text."""
    for path in sorted([*ROOT.glob("wmrjax/cli/*.py"), *ROOT.glob("paper/*.py"), *ROOT.glob("benchmarks/*.py")]):
        text = path.read_text()
        uses_jax = re.search(r"^(import|from) (jax|wmrjax|paper)\b", text, re.M)  # not a driver of processes
        if "\ndef main(" in text and path.name != "__init__.py" and uses_jax:  # wmrjax.cli.main dispatches to a job's
            yield path.relative_to(ROOT), text


def test_every_command_line_calls_configure_xla_in_main():
    mains = dict(_mains())
    assert len(mains) == 18, sorted(mains)
    for path, text in mains.items():
        body = text[text.index("def main(") :]
        uses_tracking_cli = "common.tracking_cli(" in body
        assert uses_tracking_cli or "machine.configure_xla(" in body, path
    common = (ROOT / "paper" / "common.py").read_text()
    assert "machine.configure_xla()" in common[common.index("def tracking_cli(") :]
