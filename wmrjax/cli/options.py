"""What every command line of this project shares: argument types that refuse bad values at
parse time, cross-argument checks, the output directory made and test-written before any
work, progress lines while long stages run, and how a failed run ends.

The experiments (``python -m experiments.*``) and the tuner (``wmrjax tune``) build
their parsers with :func:`parser` and declare each option with one of the types below, so a
bad value stops the program in milliseconds with ``argument --name: ...`` naming the option
and the expected form, before JAX compiles anything. Nothing here imports JAX at module level.

Exit statuses: 2 with the usage text for a bad option (argparse's own errors and the checks
made with :func:`fail` before the work starts); 1 for an error of the work itself (a
``ValueError`` raised by it, see :func:`work`): ``PROG: error: MESSAGE`` without the usage,
its traceback shown with ``--verbose``.
"""

from __future__ import annotations

import _thread
import argparse
import atexit
import math
import os
import re
import signal
import sys
import threading
import time
import tomllib
import traceback
import uuid
import warnings
from contextlib import contextmanager
from pathlib import Path

import jax

from wmrjax import _files as files
from wmrjax import examples, resources, xla_cpu

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


def problem_file(text: str) -> Path:
    """A problem file, or the name of a shipped example (:mod:`wmrjax.examples`: ``s_path``)."""
    path = Path(text)
    if path.suffix or os.sep in text or path.exists():
        return path
    try:
        return examples.problem_file(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


_DOTTED_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def key_value(text: str) -> tuple:
    """``KEY=VALUE``: a dotted key of the problem file and a TOML value (``0.02``, ``[5.5, 1.0]``,
    ``"(1,1)"``); a value that is not TOML is taken as a string (``robot.type=(1,1)``)."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not _DOTTED_KEY.fullmatch(key):
        raise argparse.ArgumentTypeError(
            f"expected KEY=VALUE with a dotted key (plant.control_period=0.02), got {text!r}"
        )
    try:
        return key, tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        return key, value.strip()


def add_set(p: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable): one value of the problem file by its dotted key, applied
    after the job's own options (see :func:`with_set`)."""
    p.add_argument(
        "--set",
        dest="set_values",
        type=key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="set one value of the problem file by its dotted key, a TOML value (--set plant.control_period=0.02, "
        "--set plant.input_limit=[5.5,1.0]); repeat for several; applied after the other options",
    )


def with_set(problem, args):
    """The problem with ``--set`` applied (:meth:`wmrjax.problem.Problem.with_values`, validated
    when the job reads its setting)."""
    values = dict(args.set_values)
    return problem.with_values(values) if values else problem


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help text with each option's default appended."""


def default_cache_dir() -> Path:
    """Where compiled programs are kept between runs: ``$XDG_CACHE_HOME/wmrjax/xla`` (``~/.cache/...``)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "wmrjax" / "xla"


def parser(description: str, default_out: str | None, compile_cache: bool = True) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` whose help shows defaults, with ``--out`` when ``default_out`` is given,
    the persistent compilation cache options (see :func:`use_compilation_cache`) and ``--verbose``
    (see :func:`work`)."""
    p = argparse.ArgumentParser(description=description, formatter_class=_Formatter)
    if default_out is not None:
        p.add_argument("--out", type=Path, default=Path(default_out), help="output directory (created if missing)")
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


def fail(p: argparse.ArgumentParser, message: str):
    """Exit like argparse does for a bad argument (status 2, usage and message on stderr): for
    checks of the options made before the work starts, not for errors of the work (:func:`work`)."""
    p.error(message)


def fail_work(p: argparse.ArgumentParser, message: str, verbose: bool = False):
    """Exit for an error of the work itself: status 1 and ``PROG: error: MESSAGE`` on stderr,
    without the usage text (the options were fine). With ``verbose``, the traceback of the
    exception being handled is printed first; without, the line says that ``--verbose`` shows it."""
    if verbose:
        traceback.print_exc(file=sys.stderr)
    else:
        message += " (rerun with --verbose for the traceback)"
    sys.stderr.flush()
    p.exit(1, f"{p.prog}: error: {message}\n")


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


def prepare_output(p, out: Path, lock: bool = True) -> Path:
    """Create ``out``, prove it writable (write and delete a probe file) and, with ``lock``, make
    this process its one writer until it exits (:func:`wmrjax._files.acquire_output`: a second run
    into the same directory is refused, naming the first; temporary files of a killed write are
    removed); exits with a usage error if any of this fails. The lock's token is
    ``os.environ[wmrjax._files.LOCK_ENV]`` afterwards, for worker processes."""

    out = Path(out)
    if out.exists() and not out.is_dir():
        fail(p, f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{uuid.uuid4().hex}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        fail(p, f"--out {out} is not a writable directory ({exc.strerror or exc})")
    if lock:
        try:
            token = files.acquire_output(out, " ".join([Path(sys.argv[0]).name] + sys.argv[1:]))
        except files.OutputLocked as exc:
            fail(p, str(exc))
        if token is not None:
            os.environ[files.LOCK_ENV] = token
            atexit.register(files.release_output, out, token)
            try:
                files.claim_output(out, job_name(p))
            except files.OutputLocked as exc:
                fail(p, str(exc))
    return out


def job_name(p) -> str:
    """The running job (``wmrjax sweep``), else the module ``python -m`` ran (``paper.section_6_1``),
    else the parser's program name: what :func:`wmrjax._files.claim_output` records."""
    if p.prog.startswith("wmrjax "):  # a job of the wmrjax command
        return p.prog
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    name = getattr(spec, "name", None)
    if name:
        return name.removesuffix(".__main__")
    return p.prog


def work(p, args, fn, hint=lambda message: message):
    """Run a command's work: ``--out`` made and test-written, the compilation cache on, a
    heartbeat, and ``fn(progress)`` called with the heartbeat's ``stage``; returns its result.

    A ``ValueError`` raised by the work is an error of the work, not a bad option: it ends the
    program through :func:`fail_work` (status 1, ``PROG: error: MESSAGE`` without the usage
    text; its traceback with ``--verbose``); ``hint`` may add advice to the message. Other
    exceptions propagate with their traceback. Check the options (:func:`fail`) before this."""
    prepare_output(p, args.out)
    use_compilation_cache(args)
    try:
        with reliable_interrupt(), heartbeat() as hb:
            return fn(hb.stage)
    except ValueError as exc:
        fail_work(p, hint(str(exc)), verbose=getattr(args, "verbose", False))
    except KeyboardInterrupt:
        interrupted(p, args.out)


# [s] how often an interrupt that Python dropped is raised again in the main thread
INTERRUPT_RETRY_S = 0.5


@contextmanager
def reliable_interrupt():
    """Make Ctrl-C end the work: Python raises KeyboardInterrupt at the main thread's next
    bytecode, and when that is one of jaxlib's garbage-collection callbacks the exception is
    printed and dropped ("Exception ignored in ... _xla_gc_callback") and the run went on to
    the end with status 0. Here a first SIGINT also starts a thread that raises it again every
    :data:`INTERRUPT_RETRY_S` until the main thread leaves this block. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending = threading.Event()
    done = threading.Event()

    def again():
        while not done.wait(INTERRUPT_RETRY_S):
            _thread.interrupt_main()

    def handler(signum, frame):
        if not pending.is_set():
            pending.set()
            threading.Thread(target=again, daemon=True).start()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        done.set()
        signal.signal(signal.SIGINT, previous)


def interrupted(p: argparse.ArgumentParser, out) -> None:
    """Exit 130 (the shell's code for SIGINT) with one line instead of a traceback: every result
    is written atomically and the lock is released at exit, so what finished is kept and the
    same command resumes from it (a sweep's blocks, the tuner's checkpoint)."""
    sys.stderr.flush()
    p.exit(
        130,
        f"{p.prog}: interrupted; what finished is kept in {out} (written atomically): run the same command "
        "again to resume\n",
    )


# --- progress --------------------------------------------------------------------------------------


class Heartbeat:
    """Prints the current stage when it starts and every ``every`` seconds while it runs.

    Use as a context manager around a command's work and call :meth:`stage` at each long
    step; a daemon thread prints ``[  12 s] still working (last: <stage>)`` so that no stage
    (JAX's compilation included) stays silent for more than ``every`` seconds.
    """

    def __init__(self, every: float = 10.0, stream=None):
        self.every = every
        self.stream = stream if stream is not None else sys.stdout
        self._stage = "starting"
        self._t0 = time.perf_counter()
        self._last = self._t0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _say(self, text: str) -> None:
        with self._lock:
            print(f"[{time.perf_counter() - self._t0:6.0f} s] {text}", file=self.stream, flush=True)
            self._last = time.perf_counter()

    def stage(self, text: str) -> None:
        """Announce a new stage (e.g. ``"compiling and running the batch rollout"``)."""
        self._stage = text
        self._say(text)

    def _run(self) -> None:
        while not self._stop.wait(min(0.5, self.every / 4)):
            if time.perf_counter() - self._last >= self.every:
                self._say(f"still working (last: {self._stage})")

    def __enter__(self) -> "Heartbeat":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


@contextmanager
def heartbeat(every: float = 10.0):
    """``with heartbeat() as hb: hb.stage("..."); ...``: see :class:`Heartbeat`."""
    with Heartbeat(every) as hb:
        yield hb
