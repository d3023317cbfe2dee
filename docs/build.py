"""``make docs``: Sphinx with warnings as errors, the tutorials executed by two parallel readers.

Each reader starts its notebooks' Jupyter kernels. jupyter_client picks a kernel's TCP ports by
binding free ones and releasing them before the kernel binds them, so two processes that start
kernels at the same moment can pick the same port (seen once, in a fresh clone: ZMQError
"Address already in use", then "Kernel didn't respond in 60 seconds"). That failure, and only
it, gets one more build from a fresh environment (``-E``: every page read again, so every
warning is reported again; the notebooks that did execute come from the execution cache). Any
other failure, or the same one twice, fails the build.
"""

from __future__ import annotations

import subprocess
import sys

SPHINX = [sys.executable, "-m", "sphinx", *"-b html -W --keep-going -j 2 -q docs docs/_build/html".split()]
# what the kernel-port race prints (ipykernel's bind error, then nbclient's time-out)
RACE = ("Address already in use", "Kernel didn't respond")


def build(command: list) -> tuple[int, bool]:
    """Run ``command``, its output passed through: ``(exit status, whether it showed the race)``."""
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    race = False
    for line in proc.stdout:
        sys.stdout.write(line)
        race = race or any(s in line for s in RACE)
    return proc.wait(), race


def main(command: list = SPHINX) -> int:
    status, race = build(command)
    if status and race:
        print("docs: a notebook's kernel did not start (two kernels took one port): building once more", flush=True)
        status, _ = build(command + ["-E"])
    return status


if __name__ == "__main__":
    sys.exit(main())
