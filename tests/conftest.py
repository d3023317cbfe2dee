"""Test configuration: float64 everywhere, strict dtype promotion (no silent int/float or
float32/float64 mixing), shared (module-scoped) closed loops."""

import os
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One compilation cache for this test session, shared by the xdist workers and by the command
# lines the tests start (through XDG_CACHE_HOME, where they keep it): a program compiled once
# in the session is loaded after that, and the tests never touch the user's own cache.
_SESSION = os.environ.get("PYTEST_XDIST_TESTRUNUID") or f"pid{os.getpid()}"
_CACHE_HOME = os.path.join(tempfile.gettempdir(), f"wmrjax-tests-{_SESSION}")
os.environ["XDG_CACHE_HOME"] = _CACHE_HOME
jax.config.update("jax_compilation_cache_dir", os.path.join(_CACHE_HOME, "wmrjax", "xla"))
# every program, the small ones too: the command lines the tests start store theirs, and read the
# workers' (tests/test_experiments.py, test_tuning.py, test_export.py, test_problem.py: 163 -> 155 s)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)

# XLA's lowest backend (LLVM) optimization level for the programs of the test session: the tests
# check values, not speed, and this suite is mostly compiling (test_autodiff.py and
# test_static.py: 185 -> 145 CPU s; make test from a fresh clone 26:18 -> 23:06 CPU min). Values agree with the
# default level to rounding (the library compiles some programs at levels 0 and 1 itself); the
# tests that compare such a program with a default-level one pin that side to DEFAULT_OPT_LEVEL.
# The command lines the tests start inherit the level through XLA_FLAGS. WMRJAX_TEST_OPT_LEVEL=default runs the whole
# session at the default level (docs/development.md).
DEFAULT_OPT_LEVEL = {"xla_backend_optimization_level": 3}  # XLA's default (its DebugOptions)
# XLA:CPU's legacy elemental emitters too, not its MLIR fusion emitters: they compile this suite's
# programs a third faster (the saturation search's enclosure 45 -> 31 s, tests/test_forward_car.py
# 148 -> 121 s alone, 2 cores) to the same values within rounding. The library keeps XLA's default but for
# its enclosures' programs, which choose these emitters themselves (wmrjax.certify.saturation.SEARCH_COMPILE).
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
if os.environ.get("WMRJAX_TEST_OPT_LEVEL", "0") != "default":
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + TEST_XLA_FLAGS).strip()

# The command lines' XLA:CPU setting (every time loop compiled into one kernel, wmrjax.xla_cpu), so
# that the tests run the programs the command lines run, in-process and in the processes they start.
from wmrjax.xla_cpu import configure_cpu  # noqa: E402

configure_cpu()

import math  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import wmrjax as w  # noqa: E402
from wmrjax import references  # noqa: E402

S2 = math.sqrt(2.0)


@pytest.fixture
def returns(monkeypatch):
    """``returns(module, name)``: patch ``module.name`` to record what each call returns (a command
    line's job report, as the command line got it); returns that list."""

    def attach(module, name: str) -> list:
        real, results = getattr(module, name), []

        def recorded(*args, **kw):
            results.append(real(*args, **kw))
            return results[-1]

        monkeypatch.setattr(module, name, recorded)
        return results

    return attach


@pytest.fixture
def rng():
    """A fresh generator per test: its draws do not depend on which tests ran before it in the
    same worker (pytest-xdist distributes them differently from run to run)."""
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def paper61():
    """The §6.1 set-up: (2,0) robot, e = 0, reference (62), poles at -1, IC (63)."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(references.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))
    zref = ctrl.reference_state(0.0, params)
    vel = -(2 * S2 + S2 / 2)  # xdot_ref(0) = ydot_ref(0) = -3.5355 m/s
    zeta0 = jnp.array([[zref[0] - 0.54, zref[1] + 0.54], [vel, vel]])
    z0 = ctrl.initial_state(zeta0, params)
    return ctrl, params, z0


# pytest-xdist (--dist loadfile) hands whole files to the workers, and the run ends when the last
# file does: the files that take longest go first (measured at 9ecbec5, 2 cores, heaviest first),
# so that the two workers finish together instead of one waiting for a long file started last.
HEAVY_FIRST = (
    "test_mismatch.py",
    "test_saturation.py",
    "test_certify_real_loop.py",
    "test_forward_car.py",
    "test_certify.py",
    "test_sweep.py",
    "test_samples.py",
    "test_dynamic.py",
    "test_scalarize.py",
    "test_tuning.py",
    "test_simulate.py",
    "test_static.py",
    "test_experiments_bench.py",
    "test_autodiff.py",
    "test_output_safety.py",
    "test_tuning_certified.py",
    "test_hoist.py",
    "test_math.py",
    "test_certify_tightness.py",
    "test_export.py",
    "test_linearize.py",
    "test_experiments.py",
    "test_guards.py",
    "test_cli.py",
)
# Files whose tests compile the same heavy programs (the circle loop's saturation search, 45 s of
# compiling) are one work unit: one worker runs them one after the other and finds the programs
# compiled in its own process (two workers would compile them twice, at once, on two cores).
SHARED_UNITS = dict.fromkeys(
    ("test_mismatch.py", "test_saturation.py", "test_certify_real_loop.py"), "certification of the circle loop's plant"
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(HEAVY_FIRST)))  # stable: file order kept


def pytest_xdist_make_scheduler(config, log):
    """--dist loadfile with :data:`SHARED_UNITS` and the files in collection order (xdist's own
    order, by number of tests, would undo :data:`HEAVY_FIRST`)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling  # pytest-xdist: loaded by a parallel session only

    class Scheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return SHARED_UNITS.get(path.rsplit("/", 1)[-1], path)

    config.option.loadscopereorder = False
    return Scheduling(config, log)
