"""Oracle builders: the common shapes of "what a user should see".

Every builder returns ``oracle(run) -> (outcome, evidence)``. The rules (the probe's page,
``docs/commands/probe.md``):

* GOOD -- refused with a clear message (a ``ValueError`` naming what was wrong; a command line's
  exit status 1 or 2 with a one-line ``error:`` message, no traceback), before any time loop was
  traced where the case demands it; or the correct answer, by the case's own check.
* POOR -- refused, but late (after the work started) or unclearly (a raw exception of another type,
  a traceback, a message that does not name the cause, a C++ abort); or accepted where a refusal
  was due but the answer is not wrong.
* BAD -- data loss, mixed results, a silently wrong answer (no error, a wrong result), or a hang
  past the timeout where a refusal was due.
"""

from __future__ import annotations

import re

from tests.probe.harness import BAD, GOOD, LATE_CPU_S, POOR, Run


def short(text, n: int = 220) -> str:
    """``text`` on one line, at most ``n`` characters (evidence strings)."""
    return " ".join(str(text).split())[:n]


def _exc_text(run: Run) -> str:
    e = run.exc or {}
    return f"{e.get('type')}: {short(e.get('message', ''), 200)}"


def hang(run: Run, due: str = BAD) -> tuple[str, str]:
    """A case that ran past its timeout: BAD where a refusal was due (the default)."""
    out = [x for x in run.stdout.splitlines() if x.strip() and not x.startswith("PROBE_")]
    last = run.last_line or (out[-1].strip() if out else "")
    said = f"; its last output: {short(last, 160)}" if last else "; no output"
    return due, f"no answer after {run.seconds:.0f} s, {run.cpu_seconds:.0f} CPU s (killed at the timeout){said}"


def library_refusal(run: Run, pattern: str, early: bool = True) -> tuple[str, str] | None:
    """GOOD/POOR for a snippet that raised (None when it did not raise).

    GOOD: a ValueError matching ``pattern`` (case-insensitive), and, with ``early``, no time
    loop traced since ``arm()``. POOR: any other exception, a message that does not match, a
    late refusal, or a crash without a Python exception.
    """
    if run.exc is None:
        if run.rc not in (0, None):
            return POOR, f"crashed with exit status {run.rc}: {short(run.stderr[-300:])}"
        return None
    msg = run.exc.get("message", "")
    if not run.exc.get("value_error"):
        return POOR, f"raw {_exc_text(run)}"
    if not re.search(pattern, msg, re.I | re.S):
        return POOR, f"ValueError not naming the cause: {short(msg)}"
    if early and (run.exc.get("traced") or run.cpu_seconds > LATE_CPU_S):
        return POOR, f"refused late (after the work started, {run.cpu_seconds:.0f} CPU s): {short(msg)}"
    return GOOD, f"refused: {short(msg)}"


def refuses(pattern: str, early: bool = True, accepted=BAD, timeout=BAD):
    """A snippet must raise a ValueError matching ``pattern``.

    Args:
      pattern: a regular expression (case-insensitive) the message must match: what was wrong.
      early: the refusal must come before the work (no time loop traced after ``arm()``, at most
        :data:`~tests.probe.harness.LATE_CPU_S` CPU seconds).
      accepted: the outcome when the snippet returns normally, or a function of the run giving
        ``(outcome, evidence)`` (to tell a harmless acceptance from a wrong answer).
      timeout: the outcome of a run killed at the timeout.

    Returns:
      The oracle, ``oracle(run) -> (outcome, evidence)``.
    """

    def oracle(run: Run):
        if run.timed_out:
            return hang(run, timeout)
        verdict = library_refusal(run, pattern, early)
        if verdict is not None:
            return verdict
        if callable(accepted):
            return accepted(run)
        return accepted, f"accepted without error: {short(run.results)}"

    return oracle


def answer(check, refusal: str | None = None, early: bool = True, timeout=BAD):
    """A snippet must return the right answer: ``check(results) -> (ok, evidence)``.

    GOOD when it holds; BAD when the snippet returned a wrong answer without error; a refusal
    matching ``refusal`` (if given) is GOOD too, any other exception POOR.
    """

    def oracle(run: Run):
        if run.timed_out:
            return hang(run, timeout)
        if run.exc is not None or run.rc not in (0, None):
            if refusal is not None:
                return library_refusal(run, refusal, early) or (POOR, "failed")
            return POOR, f"failed: {_exc_text(run) if run.exc else short(run.stderr[-300:])}"
        ok, evidence = check(run.results)
        return (GOOD if ok else BAD), evidence

    return oracle


def raised(stderr: str) -> str:
    """The exception a traceback ends with (its last line naming an Error or Exception)."""
    lines = [x.strip() for x in stderr.splitlines() if re.match(r"^[\w.]*(Error|Exception|Interrupt)\b", x.strip())]
    return lines[-1] if lines else (stderr.strip().splitlines() or [""])[-1]


def cli_message(run: Run) -> str:
    """The message of a refused command line: its last ``error:`` line."""
    for line in reversed(run.stderr.splitlines()):
        if "error:" in line:
            return line.strip()
    return run.last_line


def cli_refusal(run: Run, pattern: str, early: bool = True, codes=(1, 2)) -> tuple[str, str] | None:
    """GOOD/POOR for a command line that exited non-zero (None when it exited 0)."""
    if run.rc == 0:
        return None
    msg = cli_message(run)
    if run.rc not in codes:
        return POOR, f"exit status {run.rc} (a crash, not a refusal): {short(raised(run.stderr))}"
    if "Traceback (most recent call last)" in run.stderr:
        return POOR, f"exit {run.rc} with a raw traceback: {short(raised(run.stderr))}"
    if not re.search(pattern, msg, re.I | re.S):
        return POOR, f"exit {run.rc}, message not naming the cause: {short(msg)}"
    if early and run.late:
        return POOR, f"exit {run.rc}, refused late (after the work started, {run.cpu_seconds:.0f} CPU s): {short(msg)}"
    return GOOD, f"exit {run.rc}: {short(msg)}"


def cli_refuses(pattern: str, early: bool = True, accepted=BAD, timeout=BAD, codes=(1, 2)):
    """A command line must exit 1 or 2 with one ``error:`` line matching ``pattern``.

    Args:
      pattern, early, accepted, timeout: as for :func:`refuses`.
      codes: the exit statuses of a refusal.

    Returns:
      The oracle, ``oracle(run) -> (outcome, evidence)``.
    """

    def oracle(run: Run):
        if run.timed_out:
            return hang(run, timeout)
        verdict = cli_refusal(run, pattern, early, codes)
        if verdict is not None:
            return verdict
        if callable(accepted):
            return accepted(run)
        return accepted, f"exit 0 (accepted): {short(run.last_line)}"

    return oracle


def cli_succeeds(check=None, timeout=BAD):
    """A command line must exit 0 and, where given, ``check(run) -> (ok, evidence)`` must hold
    (a wrong result is BAD); a failure is POOR."""

    def oracle(run: Run):
        if run.timed_out:
            return hang(run, timeout)
        if run.rc != 0:
            return POOR, f"exit {run.rc}: {short(cli_message(run))}"
        if check is None:
            return GOOD, f"exit 0: {short(run.last_line)}"
        ok, evidence = check(run)
        return (GOOD if ok else BAD), evidence

    return oracle
