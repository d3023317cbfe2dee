"""One resource model: the memory a run, a batch of runs or a sweep block will need, checked
against the machine before anything compiles.

The model counts the arrays that grow with the problem and multiplies them by factors
measured on this code (growth of the peak resident memory over a warm baseline, float64, CPU;
the measurements are on the docs' benchmarks page and in ``tests/test_resources.py``):

* a saved sample of one run: the state (n), the control (at most n), the margin, the valid
  flag and the time, and the copy handed back to NumPy: ``(2 n + SAMPLE_EXTRA_FLOATS)``
  floats (measured 120-150 B at n = 4: the smaller the run, the larger its share of fixed buffers);
* a point of the reference check's grid (every ``REFERENCE_GRID_STEP / 2`` s of the horizon):
  the reference's jet, its time, regularity and branch, held twice while the blocks are
  joined and again by the kink test: ``GRID_COPIES * (jet + 3)`` floats (measured 157 B for
  a velocity-level law of two outputs, 216 B at torque level);
* a step of a reverse-mode gradient: the carry kept for the backward pass,
  :data:`GRADIENT_CARRY_COPIES` states per run and step;
* a process: JAX, XLA and the compiled programs, :data:`PROCESS_BYTES`.

The estimate is an upper bound within :data:`ESTIMATE_FACTOR` of the measured peak
(:data:`GRADIENT_ESTIMATE_FACTOR` for a gradient step; a test holds it to that); it is deliberately conservative: a refused run that would have fit costs
the user a smaller ``save_every``, an accepted one that does not fit costs the machine.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

# floats per saved sample beyond the state and the control (margin, valid, time, NumPy copy)
SAMPLE_EXTRA_FLOATS = 11
# copies of the reference check's grid alive at its peak (the blocks, their concatenation, the kink test)
GRID_COPIES = 2.5
# floats per grid point beside the jet: time, regularity, branch
GRID_EXTRA_FLOATS = 3
# copies of a step's carry reverse mode keeps, per run and step (measured on section 6.1's sampled
# loop, 13 states, 1000 steps, one process going from 64 to 2048 training scenarios: 91-180 MB
# more over six runs, 46-91 B per scenario-step, where one carry is 104 B)
GRADIENT_CARRY_COPIES = 1.25  # one carry and a margin for the run-to-run spread
# one JAX process with its compiled programs (measured: 0.53 GB resident after importing wmrjax
# and a first simulate of the section 6.1 loop; the probe: 0.6 GB per sweep process)
PROCESS_BYTES = 0.6e9
# the estimate is above the measured peak and at most this factor above it (runs, sweeps)
ESTIMATE_FACTOR = 2.0
# the same for a gradient step, whose measured growth varies from run to run (91-180 MB for the
# same step: how much the allocator reuses across XLA's buffers)
GRADIENT_ESTIMATE_FACTOR = 4.0
# what a run may take of the memory available now (the rest: the OS, the caller's own arrays)
USABLE_FRACTION = 0.8


class Estimate(NamedTuple):
    """Memory a piece of work needs [bytes].

    Attributes:
      device: the runs' arrays on the devices, all of them (host devices share the machine's
        memory): saved samples, carries kept for reverse mode.
      host: arrays on the host beside them (the reference check, NumPy copies).
      processes: processes to start (each :data:`PROCESS_BYTES`).
    """

    device: float
    host: float
    processes: int = 0

    @property
    def total(self) -> float:
        """Everything on one machine: devices' and host arrays and the processes [bytes]."""
        return self.device + self.host + self.processes * PROCESS_BYTES


def available_bytes() -> int | None:
    """Memory available to a new allocation now [bytes], None where unknown: the least of the
    machine's (``MemAvailable`` on Linux, else the physical memory), what the process's control
    group may still take (cgroup v2 ``memory.max`` or v1 ``memory.limit_in_bytes``, less its
    current use: a container's or a batch job's limit) and what its address-space limit
    (``ulimit -v``) leaves beside the address space it holds."""
    found = [x for x in (_machine_available(), _cgroup_available(), _address_space_available()) if x is not None]
    return min(found) if found else None


def _machine_available() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # pragma: no cover - non-POSIX
        return None


def _read_int(path: str) -> int | None:
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # "max": no limit


# a cgroup v1 memory limit at or above this is the kernel's "unlimited" (a page-rounded 2^63)
_CGROUP_V1_UNLIMITED = 2**62


def _cgroup_available() -> int | None:
    """The process's control group's memory limit less its use [bytes], None without a limit."""
    try:
        with open("/proc/self/cgroup") as fh:
            lines = fh.read().splitlines()
    except OSError:
        return None
    for line in lines:
        hier, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if hier == "0" and controllers == "":  # v2: one unified hierarchy
            base = "/sys/fs/cgroup" + path.rstrip("/")
            limit, used = _read_int(base + "/memory.max"), _read_int(base + "/memory.current")
        elif "memory" in controllers.split(","):  # v1: the memory controller's hierarchy
            base = "/sys/fs/cgroup/memory" + path.rstrip("/")
            limit, used = _read_int(base + "/memory.limit_in_bytes"), _read_int(base + "/memory.usage_in_bytes")
            limit = None if limit is not None and limit >= _CGROUP_V1_UNLIMITED else limit
        else:
            continue
        if limit is not None:
            return max(0, limit - (used or 0))
    return None


def _address_space_available() -> int | None:
    """``RLIMIT_AS`` less the address space the process holds (``VmSize``) [bytes], None if unlimited."""
    try:
        import resource  # POSIX only: absent on Windows

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):  # pragma: no cover - non-POSIX
        return None
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    held = 0
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    held = int(line.split()[1]) * 1024
    except OSError:
        pass
    return max(0, soft - held)


def samples_bytes(n_samples: int, n_state: int, itemsize: int = 8, runs: int = 1) -> float:
    """The saved samples of ``runs`` runs of ``n_samples`` samples each [bytes]."""
    return float(runs) * n_samples * (2 * n_state + SAMPLE_EXTRA_FLOATS) * itemsize


# [s] spacing of the grid on which a law checks its reference (wmrjax.controllers.law, which
# imports it): here, where the check's memory is sized, so that this module imports no law
REFERENCE_GRID_STEP = 0.01


def check_bytes(horizon: float, jet_floats: int) -> float:
    """The reference check over ``horizon`` seconds of a law whose reference jet has
    ``jet_floats`` numbers per time (0: a system without a reference check) [bytes]."""
    if jet_floats <= 0 or not np.isfinite(horizon):
        return 0.0
    points = horizon / (REFERENCE_GRID_STEP / 2) + 2  # both parities of the check's grid
    return points * GRID_COPIES * (jet_floats + GRID_EXTRA_FLOATS) * 8


def run_estimate(
    system, *, n_steps: int, save_every: int, n_state: int, itemsize: int, horizon: float, runs: int = 1
) -> Estimate:
    """One call of :func:`wmrjax.simulate` (or ``runs`` of them batched): saved samples on the
    device, the reference check on the host."""
    samples = n_steps // save_every + 1
    return Estimate(
        samples_bytes(samples, n_state, itemsize, runs), check_bytes(horizon, system.reference_jet_floats())
    )


def gradient_bytes(runs: int, n_steps: int, n_state: int, itemsize: int = 8) -> float:
    """Reverse-mode memory of a loss over ``runs`` runs of ``n_steps`` steps [bytes]: the scan
    keeps each step's carry (the state, :data:`GRADIENT_CARRY_COPIES` times) for the backward pass."""
    return float(runs) * n_steps * n_state * GRADIENT_CARRY_COPIES * itemsize


def check_fits(estimate: Estimate, what: str, fix: str) -> None:
    """ValueError when ``estimate`` exceeds :data:`USABLE_FRACTION` of the memory available now.

    Args:
      estimate: the work's :class:`Estimate`.
      what: the work, for the message (e.g. ``"n_steps = 10000000 with save_every = 1"``).
      fix: how to make it smaller (e.g. ``"raise dt or save_every"``).
    """
    have = available_bytes()
    if have is None:
        return
    if estimate.total > USABLE_FRACTION * have:
        parts = [
            f"{v / 1e9:.3g} GB {name}"
            for v, name in ((estimate.device, "of run arrays"), (estimate.host, "on the host"))
            if v > 0
        ]
        if estimate.processes:
            parts.append(f"{estimate.processes} processes of {PROCESS_BYTES / 1e9:.2g} GB")
        raise ValueError(
            f"{what} needs about {estimate.total / 1e9:.3g} GB ({', '.join(parts)}), more than "
            f"{USABLE_FRACTION:.0%} of the {have / 1e9:.3g} GB of memory available now: {fix}"
        )
