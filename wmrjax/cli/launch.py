"""A sweep over several local processes: the launcher starts them (``jax.distributed`` over
127.0.0.1), passes each the command line it was given, and stops them all when one fails or
it is itself interrupted or killed."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

__all__ = ["POLL_S", "die_with_parent", "launch"]


def launch(a, devices: int) -> int:
    """Start ``--processes`` local processes (jax.distributed over 127.0.0.1) and wait for them.

    Args:
      a: the launcher's arguments (``a.argv`` the command line it was given).
      devices: JAX host devices per process.

    Returns:
      0 when every process finished, else the first failed one's exit code.
    """
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = [
        sys.executable,
        "-m",
        "wmrjax",
        "sweep",
        *_without_processes(a.argv),
        "--out",
        str(a.out),
        "--devices",
        str(devices),
        "--coordinator",
        f"127.0.0.1:{port}",
        "--num-processes",
        str(a.processes),
    ]
    if a.no_compile_cache:
        base.append("--no-compile-cache")
    elif a.compile_cache is not None:
        base += ["--compile-cache", str(a.compile_cache)]
    procs = [subprocess.Popen(base + ["--process-id", str(i)], preexec_fn=die_with_parent) for i in range(a.processes)]
    try:
        return _wait(procs, a)
    except BaseException:  # Ctrl-C or a kill of the launcher: its workers do not outlive it
        for pr in procs:
            if pr.poll() is None:
                pr.terminate()
        raise


def _without_processes(argv: list) -> list:
    """The launcher's arguments less ``--processes N`` (a worker is one process of the run)."""
    out, skip = [], False
    for tok in argv:
        if skip:
            skip = False
        elif tok == "--processes":
            skip = True
        elif not tok.startswith("--processes="):
            out.append(tok)
    return out


def die_with_parent() -> None:
    """In a worker, before it runs: ask Linux to send it SIGTERM when its launcher dies (even by
    SIGKILL), so that no orphan keeps computing and later overwrites the next command's table
    and summary under a lock it no longer has. Elsewhere a no-op (the launcher still stops
    its workers on any exception)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes  # Linux only: prctl(PR_SET_PDEATHSIG)

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


# how often the launcher looks at its processes [s]
POLL_S = 0.2


def _wait(procs: list, a) -> int:
    """Wait for the local processes; when one fails, stop the others at once (they would wait
    at the next barrier for minutes and abort with a stack dump) and say how to resume."""
    while True:
        codes = [pr.poll() for pr in procs]
        bad = [i for i, c in enumerate(codes) if c not in (None, 0)]
        if bad or all(c == 0 for c in codes):
            break
        time.sleep(POLL_S)
    if not bad:
        return 0
    for pr in procs:
        if pr.poll() is None:
            pr.terminate()
    for pr in procs:
        try:
            pr.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pr.kill()
            pr.wait()
    print(
        f"process {bad[0]} of {len(procs)} failed (exit code {codes[bad[0]]}); the others were stopped. Finished "
        f"blocks are kept in {a.out}: run the same command again to resume",
        file=sys.stderr,
    )
    return codes[bad[0]] if codes[bad[0]] > 0 else 1
