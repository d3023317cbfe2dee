"""How a job runs: its output directory made, test-written and locked before any work, the
work with its progress lines (a heartbeat while a long stage runs), and how it ends (exit 1
with ``PROG: error: MESSAGE`` for an error of the work, one line for Ctrl-C)."""

from __future__ import annotations

import _thread
import argparse
import atexit
import os
import signal
import sys
import threading
import time
import traceback
import uuid
from contextlib import contextmanager
from pathlib import Path

from wmrjax import _files as files
from wmrjax.cli.machine import use_compilation_cache
from wmrjax.cli.options import fail


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


def prepare_output(p, out: Path, lock: bool = True, fresh: bool = False) -> Path:
    """Create ``out``, prove it writable (write and delete a probe file) and, with ``lock``, make
    this process its one writer until it exits (:func:`wmrjax._files.acquire_output`: a second run
    into the same directory is refused, naming the first; temporary files of a killed write are
    removed) and claim it for this job (:func:`wmrjax._files.claim_output`: another job's results
    there are refused, or with ``fresh`` removed); exits with a usage error if any of this fails.
    The lock's token is ``os.environ[wmrjax._files.LOCK_ENV]`` afterwards, for worker processes.
    Every file this process writes there is recorded (:func:`wmrjax._files.record_writes`)."""
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
                removed = files.claim_output(out, job_name(p), fresh=fresh)
            except files.OutputLocked as exc:
                fail(p, str(exc))
            if removed:
                print(f"{out}: --fresh removed {len(removed)} files of another job's results", file=sys.stderr)
    files.record_writes(out)
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
    prepare_output(p, args.out, fresh=args.fresh)
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
    """A :class:`Heartbeat` as a context manager: its ``stage`` names what runs now."""
    with Heartbeat(every) as hb:
        yield hb
