"""``python benchmarks/peak_of.py RSS_FILE COMMAND...``: run COMMAND, write the peak resident memory
of its process tree (``ru_maxrss`` of the children, KiB) to RSS_FILE, exit with its status.

A fresh parent per command, so that the figure is that command's alone; it imports nothing but
the standard library (no JAX start-up in the measured wall time). The sweep benchmark runs it.
"""

import resource
import subprocess
import sys


def main(argv: list) -> int:
    """Run ``argv[1:]``; write its tree's peak memory to ``argv[0]``; return its exit status."""
    if len(argv) < 2:
        raise SystemExit(f"usage: peak_of.py RSS_FILE COMMAND... (got {argv})")
    r = subprocess.run(argv[1:])
    with open(argv[0], "w") as f:
        f.write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))
    return r.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
