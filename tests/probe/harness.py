"""The probe's machinery: a case, its run in a fresh process against a tree, and the outcome.

A :class:`Case` is a Python snippet (run by ``hook/probe_hook.py`` with the tree first on
``PYTHONPATH``) or a command line (``python ARGV...``), the files it needs, and an oracle: a
function of the :class:`Run` (exit status, output, exception, warnings, files written, elapsed
time, and whether a time loop was traced before the refusal) giving ``(outcome, evidence)``.
"""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

HOOK = Path(__file__).resolve().parent / "hook"
GOOD, POOR, BAD = "GOOD", "POOR", "BAD"
OUTCOMES = (GOOD, POOR, BAD)
CATEGORIES = ("data_loss", "wrong_answer", "resources", "late_or_unclear", "files", "outputs")
# environment variables of the calling shell that would change what a case does
DROP = ("PYTHONPATH", "PYTHONSTARTUP", "XLA_FLAGS", "XDG_CACHE_HOME", "WMRJAX_OUTPUT_LOCK", "WMRJAX_JAXPR_REWRITES")
KEEP_CHARS = 20_000
# CPU seconds after which a refusal is late even if no time loop was traced (the checks before
# the work ran that long: a user waited for them)
LATE_CPU_S = 30.0


@dataclass(frozen=True)
class Case:
    """One bad or hostile input and what a user should see.

    Attributes:
      id: unique name (``--only`` selects by substring).
      category: one of :data:`CATEGORIES`.
      description: what is given, in a line.
      oracle: ``oracle(run) -> (outcome, evidence)``, outcome one of :data:`OUTCOMES`.
      code: a Python snippet (see ``hook/probe_hook.py`` for the names it finds defined), or
      argv: a command line run as ``python ARGV...`` in the case's directory.
      files: name -> text or bytes, written into the case's directory first.
      prelude: ``"x64"`` (JAX in float64 and wmrjax imported), ``"x32"`` (the same, float32) or
        ``"none"`` (nothing: drivers that start their own processes).
      timeout: CPU seconds of the case's processes, or None for the probe's ``--timeout``.
      wall: a cap on the wall time [s] (default: ``--wall-factor`` times the timeout), for cases
        that may block without using the CPU (a named pipe).
      issue: True for the cases issue 34 lists.
      note: what to know when reading the outcome (a scaled-down size, an API the old tree lacks).
    """

    id: str
    category: str
    description: str
    oracle: Callable
    code: str | None = None
    argv: tuple | None = None
    files: dict = field(default_factory=dict)
    prelude: str = "x64"
    timeout: float | None = None
    wall: float | None = None
    issue: bool = False
    note: str = ""


@dataclass
class Run:
    """What one case's process did, as the oracle sees it."""

    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    timed_out: bool
    dir: Path
    results: dict
    exc: dict | None
    warnings: list
    events: list
    cpu_seconds: float = 0.0

    @property
    def traced(self) -> bool:
        """A time loop (lax.scan or lax.map) was traced after the last ``arm()`` (or at all)."""
        arms = [i for i, e in enumerate(self.events) if e.get("event") == "arm"]
        after = self.events[arms[-1] + 1 :] if arms else self.events
        return any(e.get("event") == "trace" for e in after)

    @property
    def late(self) -> bool:
        """The work had started before the answer: a time loop traced, or more than
        :data:`LATE_CPU_S` CPU seconds spent."""
        return self.traced or self.cpu_seconds > LATE_CPU_S

    @property
    def last_line(self) -> str:
        """The last non-empty line of stderr (where a command line says its error)."""
        lines = [x for x in self.stderr.splitlines() if x.strip()]
        return lines[-1].strip() if lines else ""

    def file(self, name: str) -> Path:
        """A path in the case's directory."""
        return self.dir / name


def _parse(stdout: str) -> tuple[dict, dict | None, list]:
    results, exc, warns = {}, None, []
    for line in stdout.splitlines():
        tag, _, rest = line.partition(" ")
        try:
            if tag == "PROBE_RESULT":
                results.update(json.loads(rest))
            elif tag == "PROBE_EXC":
                exc = json.loads(rest)
            elif tag == "PROBE_WARN":
                warns.append(json.loads(rest))
        except json.JSONDecodeError:
            continue
    return results, exc, warns


def _events(path: Path) -> list:
    if not path.exists():
        return []
    out = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def environment(tree: Path, work: Path) -> dict:
    """The environment of every case: the tree first on PYTHONPATH, then the hook; this run's
    own compilation cache (XDG_CACHE_HOME, which the command lines use) and fixtures (outputs
    of finished runs that several cases start from, made once); no byte-code written
    into the tree; JAX on the CPU."""
    env = {k: v for k, v in os.environ.items() if k not in DROP}
    env.update(
        PYTHONPATH=f"{tree}{os.pathsep}{HOOK}",
        XDG_CACHE_HOME=str(work / "xdg"),
        PROBE_XLA_CACHE=str(work / "xdg" / "wmrjax" / "xla"),
        PROBE_FIXTURES=str(work / "fixtures"),
        PYTHONDONTWRITEBYTECODE="1",
        JAX_PLATFORMS="cpu",
        PYTHONUNBUFFERED="1",
    )
    return env


def _limits(memory_bytes: int):
    def apply():
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))

    return apply


def _write_files(d: Path, files: dict) -> None:
    for name, content in files.items():
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content, encoding="utf-8")


def execute(case: Case, tree: Path, work: Path, timeout: float, memory_bytes: int, wall_factor: float = 4.0) -> Run:  # noqa: E501
    """Run ``case`` in a fresh process (its own session, so that its whole process tree is
    killed at the end) in a new directory under ``work``.

    The timeout counts the CPU seconds of the case's processes (a machine busy with other work
    slows a case down without making it time out), with a cap on the wall time of
    ``wall_factor`` times the timeout (a case blocked on a pipe uses no CPU at all).

    Args:
      case: the case.
      tree: the checkout under test (first on the case's ``PYTHONPATH``).
      work: the run's directory (``cases/``, ``fixtures/`` and the compilation cache in it).
      timeout: CPU seconds the case's processes may use.
      memory_bytes: the address-space limit of each of its processes.
      wall_factor: the wall-time cap, in multiples of ``timeout`` (unless the case sets ``wall``).

    Returns:
      The :class:`Run`, its directory left in place.
    """
    d = Path(tempfile.mkdtemp(prefix=re.sub(r"\W", "_", case.id)[:40] + "-", dir=work / "cases"))
    _write_files(d, case.files)
    env = environment(tree, work)
    env["PROBE_EVENTS"] = str(d / ".probe_events")
    env["PROBE_PRELUDE"] = case.prelude
    if case.code is not None:
        (d / "case.py").write_text(case.code, encoding="utf-8")
        cmd = [sys.executable, "-c", "import probe_hook; probe_hook.run('case.py')"]
    else:
        cmd = [sys.executable, *case.argv]
    t0 = time.monotonic()
    with open(d / ".stdout", "w") as out, open(d / ".stderr", "w") as err:
        p = subprocess.Popen(
            cmd,
            cwd=d,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=err,
            start_new_session=True,
            preexec_fn=_limits(memory_bytes),
        )
        try:
            timed_out, cpu = _watch(p, timeout, case.wall or wall_factor * timeout)
        finally:
            _kill_group(p.pid)  # the case's whole tree, whatever happened (an interrupted probe too)
    seconds = time.monotonic() - t0
    stdout = (d / ".stdout").read_text(errors="replace")
    stderr = (d / ".stderr").read_text(errors="replace")
    results, exc, warns = _parse(stdout)
    return Run(
        rc=None if timed_out else p.returncode,
        stdout=stdout[-KEEP_CHARS:],
        stderr=stderr[-KEEP_CHARS:],
        seconds=seconds,
        timed_out=timed_out,
        dir=d,
        results=results,
        exc=exc,
        warnings=warns,
        events=_events(d / ".probe_events"),
        cpu_seconds=cpu,
    )


def _watch(p: subprocess.Popen, cpu_limit: float, wall_limit: float) -> tuple[bool, float]:
    """Wait for ``p``, polling the CPU time of its session; (timed out, CPU seconds)."""
    t0 = time.monotonic()
    seen = {}
    before = _reaped_cpu()
    while True:
        try:
            p.wait(timeout=0.5)
            break
        except subprocess.TimeoutExpired:
            pass
        seen.update(_session_cpu(p.pid))
        if sum(seen.values()) > cpu_limit or time.monotonic() - t0 > wall_limit:
            _kill_group(p.pid)
            p.wait()
            return True, sum(seen.values())
    return False, max(sum(seen.values()), _reaped_cpu() - before)


def _session_cpu(sid: int) -> dict:
    """CPU seconds (user + system) of every live process of session ``sid``, by process id."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid:  # after the name: state, ppid, pgrp, session, ..., utime (11), stime (12)
            out[int(entry)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def _reaped_cpu() -> float:
    """CPU seconds of this process's reaped children (a finished case, with what it waited for)."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def classify(case: Case, run: Run) -> tuple[str, str]:
    """The oracle's verdict, guarded: an oracle that fails is reported, never hidden.

    Returns:
      ``(outcome, evidence)``: one of :data:`OUTCOMES` and a line of at most 400 characters.
    """
    try:
        outcome, evidence = case.oracle(run)
    except Exception as err:  # noqa: BLE001 - a broken oracle must show in the table
        return POOR, f"oracle error {type(err).__name__}: {err}"[:300]
    if outcome not in OUTCOMES:
        return POOR, f"oracle returned {outcome!r}"
    return outcome, " ".join(str(evidence).split())[:400]
