r"""What a certification will cost, said before it runs, and its counts sized to a time budget.

:func:`wmrjax.certify.analyse` spends most of its time in rollouts of the closed loop: the
empirical check, the empirical radius's rays, the falsifiers' samples, gradient starts and fine
confirmations, and whatever its caller runs after it (the slice map, the problem loop's
falsifier). Their counts follow from the settings; their time is counts times the cost of one
RK4 step of one run in a batch, which :func:`step_cost` measures on the machine, on the loop
itself (one block of the rollout program, timed after its compilation). :func:`plan` turns
both into a :class:`WorkEstimate`: seconds per stage, and the memory (:data:`MEMORY_GROWTH`
times the peak resident memory once that program has run).

The falsifiers' rollouts depend on what they find (radii tried, failures to confirm): the
estimate takes :data:`TYPICAL_ATTEMPTS` radii, and the gradient and confirmation costs are
factors measured against a batch run-step (on the issue 58 car, 2 host devices, 2026-11-29:
a gradient start-iteration 10.9 batch run-steps, a confirmation block's run-step 2.1). It is
an estimate: on that car's certification the total was within 5 % of the measured time, single
stages up to three times off (other programs' compilation overlaps them); the report keeps it
beside the measured time of each stage.

A budget (seconds) scales every count the stages are sized by (samples, rays, gradient starts
and iterations, the caller's runs) by one factor, never below the floors of :data:`FLOORS`; the falsifiers'
precision (their bisection) is not scaled, so the radii keep their tolerances.
"""

from __future__ import annotations

import math
import resource
import time
from typing import NamedTuple

import numpy as np

from wmrjax._validate import check_int
from wmrjax.certify.empirical import (
    CONFIRM_DT_FACTOR,
    RADIUS_BISECT,
    RADIUS_DIPS,
    RADIUS_GOLDEN,
    RADIUS_GRID,
    ROLLOUT_BLOCK,
    error_width,
    window_distances,
)
from wmrjax.certify.falsify import SEARCH_WINDOWS, gradient_starts
from wmrjax.resources import PROCESS_BYTES, samples_bytes

# the falsifier's radii tried per slice, typical: 10 and 13 on the issue 58 car (at most 5
# doublings and 16 bisections)
TYPICAL_ATTEMPTS = 12
# of those, the share that runs the gradient stage (the cheap stages found no failure): 6 of 10
GRADIENT_SHARE = 0.6
# fine confirmations per attempt (blocks of 16 at dt / 10), typical: 280 in 10 attempts
CONFIRMATIONS_PER_ATTEMPT = 28
# a gradient start-iteration's cost in batch run-steps, and a confirmation's per fine run-step
# (measured on the issue 58 car, 2 host devices: 10.9 and 2.1; the S-path on one host device:
# 3.3 and 6.0 for the full and position slices, and 1.0)
GRADIENT_COST = 10.9
CONFIRM_COST = 2.1
CONFIRM_STEPS = round(1.0 / CONFIRM_DT_FACTOR)  # a confirmation's steps per step of the search
# the compilation of every other program, relative to the rollout program's (cold on the car:
# Lemma 2 3.4 s, the exact maps 8.8, the falsifier's search 12.3 and confirmations 7.5, the
# problem loop's about 16, against 7.4 s)
COMPILE_RATIO = 5.0
# the whole run's peak resident memory over the peak once the rollout program is compiled and
# run (the issue 58 car, cold, two processes: 2.04 GB at the end of one, 1.23 GB after the first
# program in the other, 1.66; the other programs' compilation and the falsifier's thread): an
# upper estimate, as resources' are
MEMORY_GROWTH = 2.0
# the smallest counts a budget scales to
FLOORS = {"n_empirical": 64, "n_directions": 8, "n_starts": 4, "n_samples": 64, "steps": 8, "later": 0.1}


class Counts(NamedTuple):
    """The counts a certification's stages are sized by.

    Attributes:
      n_empirical: sampled initial errors of the empirical check.
      n_directions: rays of the position slice's empirical radius.
      n_starts: the falsifier's gradient starts per radius (0: no falsifier).
      n_samples: the falsifier's random directions per radius.
      steps: the falsifier's Adam iterations per gradient start.
      later: rollouts the caller runs after :func:`wmrjax.certify.analyse` at the same step (the
        slice map, the problem loop's falsifier).
    """

    n_empirical: int
    n_directions: int
    n_starts: int
    n_samples: int
    steps: int = 30
    later: int = 0


class WorkEstimate(NamedTuple):
    """A certification's estimated cost, before it runs.

    Attributes:
      counts: the counts it is for (after a budget's scaling).
      scale: the factor a budget applied to the counts (1: none).
      step_cost_s: measured seconds of one RK4 step of one run in a batch [s].
      compile_s: measured seconds to compile (or load) the rollout program [s].
      n_steps: RK4 steps of a run.
      stages: stage name -> (rollouts, estimated seconds).
      memory_bytes: the estimated peak resident memory of the whole run [bytes] (see :func:`plan`).
      budget_s: the budget it was fitted to (0: none).
    """

    counts: Counts
    scale: float
    step_cost_s: float
    compile_s: float
    n_steps: int
    stages: dict
    memory_bytes: float
    budget_s: float = 0.0

    def seconds(self) -> float:
        """The whole estimate [s]."""
        return float(sum(s for _, s in self.stages.values()))

    def line(self) -> str:
        """One line for the console: the total, each stage, the memory."""
        parts = ", ".join(f"{n} {s:.0f} s" for n, (_, s) in self.stages.items())
        scaled = f"; counts scaled by {self.scale:.2f} to the budget of {self.budget_s:.0f} s" if self.scale < 1 else ""
        return f"estimate: about {self.seconds():.0f} s ({parts}), {self.memory_bytes / 1e9:.2f} GB of memory{scaled}"

    def summary(self, measured: dict | None = None) -> dict:
        """Plain JSON: the estimate per stage beside ``measured`` (stage -> seconds), if given."""
        measured = measured or {}
        return {
            "estimated_s": self.seconds(),
            "stages": {
                n: {"rollouts": int(r), "estimated_s": float(s), "measured_s": measured.get(n)}
                for n, (r, s) in self.stages.items()
            },
            "memory_bytes": float(self.memory_bytes),
            "step_cost_s": float(self.step_cost_s),
            "compile_s": float(self.compile_s),
            "n_steps": int(self.n_steps),
            "counts": self.counts._asdict(),
            "scale": float(self.scale),
            "budget_s": float(self.budget_s),
        }


def peak_resident_bytes() -> float:
    """The peak resident memory of this process so far [bytes] (``getrusage``: kB on Linux)."""
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024.0


def step_cost(ctrl, params, *, dt: float, n_steps: int) -> tuple[float, float]:
    """Measure the batch rollout of the certification stages on this machine: ``(seconds per
    run-step, seconds to compile or load the program)``. One block of :data:`ROLLOUT_BLOCK`
    runs from zero initial error, called twice (the first call compiles, the second is timed);
    the program is the one the stages then use (:func:`window_distances`'s shared one)."""
    zero = np.zeros((ROLLOUT_BLOCK, error_width(ctrl)))
    t0 = time.perf_counter()
    window_distances(ctrl, params, zero, dt=dt, n_steps=n_steps)
    t1 = time.perf_counter()
    window_distances(ctrl, params, zero, dt=dt, n_steps=n_steps)
    t2 = time.perf_counter()
    run = t2 - t1
    return run / (ROLLOUT_BLOCK * n_steps), max(0.0, (t1 - t0) - run)


def plan(
    counts: Counts,
    *,
    cost: tuple[float, float],
    n_steps: int,
    n_state: int,
    budget_s: float = 0.0,
    spent_s: float = 0.0,
    resident_bytes: float = 0.0,
) -> WorkEstimate:
    """The estimate of a certification's stages, its counts scaled to fit a budget.

    Args:
      counts: the counts as asked (:class:`Counts`).
      cost: :func:`step_cost`'s ``(seconds per run-step, compile seconds)``.
      n_steps: RK4 steps of a run.
      n_state: the closed loop's state dimension.
      budget_s: seconds the whole certification may take (0: no budget, the counts as asked).
      spent_s: seconds already spent (the measurement itself).
      resident_bytes: the process's peak resident memory so far (after :func:`step_cost`); the
        memory estimate is :data:`MEMORY_GROWTH` times it, or the process and one block's
        saved samples if more.

    Returns:
      :class:`WorkEstimate`; with a budget the estimate exceeds, for the largest counts (one
      factor below 1, no count below :data:`FLOORS`) whose estimate fits what is left of it
      (at the floors when none does: the estimate then says by how much it is over).
    """
    for name, v in counts._asdict().items():
        check_int(name, v, 0)
    memory = max(
        MEMORY_GROWTH * resident_bytes, PROCESS_BYTES + samples_bytes(n_steps + 1, n_state, runs=ROLLOUT_BLOCK)
    )
    est = _estimate(counts, 1.0, cost, n_steps, memory, budget_s)
    if budget_s <= 0 or est.seconds() + spent_s <= budget_s:
        return est
    # the estimate grows with the scale, not in proportion (the confirmations and the gradient
    # stage's fixed starts do not shrink with it): bisect for the largest scale that fits
    fits = lambda x: _estimate(scaled(counts, x), x, cost, n_steps, memory, budget_s).seconds() + spent_s <= budget_s
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return _estimate(scaled(counts, lo), lo, cost, n_steps, memory, budget_s)


def scaled(counts: Counts, scale: float) -> Counts:
    """``counts`` times ``scale`` (at most 1), none below its floor (:data:`FLOORS`) nor above
    what was asked; 0 stays 0 (a stage turned off)."""
    scale = min(1.0, scale)

    def one(name, v):
        if v == 0:
            return 0
        floor = FLOORS[name] if name != "later" else math.ceil(FLOORS[name] * v)
        return int(min(v, max(floor, round(scale * v))))

    return Counts(*(one(n, v) for n, v in counts._asdict().items()))


def _estimate(counts: Counts, scale: float, cost, n_steps: int, memory: float, budget_s: float) -> WorkEstimate:
    """:class:`WorkEstimate` of ``counts`` (see :func:`plan`)."""
    c, compile_s = cost
    run = n_steps * c  # one batch run [s]
    falsifier = 0.0
    runs_per_attempt = 0
    if counts.n_starts:
        gs = gradient_starts(counts.n_starts, SEARCH_WINDOWS)
        gradient = GRADIENT_SHARE * gs * (counts.steps + 1) * run * GRADIENT_COST
        confirm = CONFIRMATIONS_PER_ATTEMPT * CONFIRM_STEPS * run * CONFIRM_COST
        falsifier = TYPICAL_ATTEMPTS * (counts.n_samples * run + gradient + confirm)
        runs_per_attempt = (
            counts.n_samples + round(GRADIENT_SHARE * gs * (counts.steps + 1)) + CONFIRMATIONS_PER_ATTEMPT
        )
    rays = counts.n_directions + 1
    blocks = lambda runs: math.ceil(runs / ROLLOUT_BLOCK)
    ray_runs = ROLLOUT_BLOCK * (
        blocks(rays * RADIUS_GRID) + (RADIUS_GOLDEN + 1) * blocks(rays * RADIUS_DIPS) + RADIUS_BISECT * blocks(rays)
    )
    stages = {
        "compiling and certificates": (0, COMPILE_RATIO * compile_s),
        "empirical check": (counts.n_empirical, counts.n_empirical * run),
        "empirical radius": (ray_runs, ray_runs * run),
        "falsifier (full)": (TYPICAL_ATTEMPTS * runs_per_attempt, falsifier),
        "falsifier (position)": (TYPICAL_ATTEMPTS * runs_per_attempt, falsifier),
        "later runs": (counts.later, counts.later * run),
    }
    return WorkEstimate(counts, scale, c, compile_s, n_steps, stages, memory, budget_s)
