"""A tuning job's settings, in small groups: what ``[tune]`` of a problem file holds.

    [tune]
    seed = 0                  # scenario draws and baseline streams
    steps = 40                # optimizer steps
    [tune.family]             # the tuned gains (wmrjax.tune.GainFamily)
    parameterization = "damping"    # or "poles" (real poles only)
    shared = true             # one polynomial for every output
    knots = 0                 # a gain schedule with K >= 2 knots on [0, t_final] (or knot_times = [...])
    min_damping = 0.0
    frozen = []               # flat indices of parameters held fixed
    [tune.loss]               # wmrjax.tune.LossWeights
    tracking = 1.0
    effort = 1e-3
    saturation = 1.0
    barrier = 1.0
    certificate = 0.0
    [tune.scenarios]          # wmrjax.tune.Scenarios
    train = 64
    validation = 32
    heldout = 64
    resample = false
    mismatch = 0.1
    [tune.optimizer]          # wmrjax.tune.Optimizer: Adam with cosine decay and clipping
    learning_rate = 0.3
    clip = 1.0
    decay_to = 0.1
    [tune.stopping]           # wmrjax.tune.Stopping
    eval_every = 5
    patience = 6
    [tune.requirement]        # wmrjax.tune.certified.Requirement (absent: none)
    radius = "initial"        # keep the exact-map radius >= this [m, m/s] ("initial": the initial gains'; "box")
    slice = "full"            # or "position"
    eps = 0.01                # the margin (default: [certify] eps, else 0.01)
    [tune.baselines]          # wmrjax.tune.Baselines
    seeds = 5
    budget = 1.0
    cma_population = 0
    cma_sigma = 0.5
    search_low = 0.2
    search_high = 5.0

Every key is optional (the defaults above); unknown keys and bad values are refused by name.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import optax

from wmrjax.problem import ProblemError, check_keys, integer, nonnegative, positive
from wmrjax.tune import certified
from wmrjax.tune.certified import Requirement
from wmrjax.tune.gains import GainFamily
from wmrjax.tune.losses import LossWeights


class Scenarios(NamedTuple):
    """How scenarios are drawn from the problem (initial errors from its ``[initial]`` box,
    references from its family, the plant around its nominal one).

    Attributes:
      train, validation, heldout: scenarios per gradient step, for early stopping and
        selection, and for the final report.
      resample: fresh training scenarios at every gradient step (a stochastic gradient).
      mismatch: +- relative error of each input scale, of e and of L, drawn per scenario.
    """

    train: int = 64
    validation: int = 32
    heldout: int = 64
    resample: bool = False
    mismatch: float = 0.1


class Optimizer(NamedTuple):
    """Adam on the unconstrained gain parameters, cosine decay of the learning rate to
    ``decay_to`` times it over the run, gradients clipped to global norm ``clip``."""

    learning_rate: float = 0.3
    clip: float = 1.0
    decay_to: float = 0.1

    def build(self, steps: int) -> optax.GradientTransformation:
        """The ``optax.GradientTransformation`` for a run of ``steps`` steps."""
        return optax.chain(
            optax.clip_by_global_norm(self.clip),
            optax.adam(optax.cosine_decay_schedule(self.learning_rate, steps, alpha=self.decay_to)),
        )


class Stopping(NamedTuple):
    """Early stopping on the validation objective, evaluated every ``eval_every`` steps."""

    eval_every: int = 5
    patience: int = 6


class Baselines(NamedTuple):
    """Random search and CMA-ES on the fixed training set.

    Attributes:
      seeds: runs of each baseline.
      budget: rollouts of a baseline run, as a multiple of the gradient's (steps x train).
      cma_population: CMA-ES population (0: 4 + floor(3 ln n)).
      cma_sigma: CMA-ES initial step in the unconstrained parameters.
      search_low, search_high: random search: rates log-uniform in [low, high] [1/s], dampings
        log-uniform in [0.3, 3].
    """

    seeds: int = 5
    budget: float = 1.0
    cma_population: int = 0
    cma_sigma: float = 0.5
    search_low: float = 0.2
    search_high: float = 5.0

    def population(self, n_parameters: int) -> int:
        """CMA-ES's population for ``n_parameters`` (Hansen's default unless set)."""
        return self.cma_population or 4 + int(np.floor(3 * np.log(n_parameters)))


class TuneSettings(NamedTuple):
    """Everything ``[tune]`` says, in groups (see the module docstring)."""

    family: dict
    loss: LossWeights
    scenarios: Scenarios
    optimizer: Optimizer
    stopping: Stopping
    baselines: Baselines
    steps: int = 40
    seed: int = 0
    requirement: Requirement | None = None

    def gain_family(self, setting) -> GainFamily:
        """The gain family for the problem's controller (knots uniform on [0, t_final] when given as a count)."""
        f = self.family
        n_knots = len(f.get("knot_times", ())) or f.get("knots", 0)
        if n_knots > setting.n_steps + 1:  # checked before np.linspace allocates them
            raise ProblemError(
                f"[tune.family] knots: {n_knots} knots on a horizon of {setting.n_steps} steps of {setting.dt} s; "
                f"at most one per step ({setting.n_steps + 1}): a schedule changes its gains between steps, "
                "and each knot adds parameters to every gradient (a few knots are the usual schedule)"
            )
        knots = tuple(float(t) for t in f.get("knot_times", ())) or (
            tuple(float(t) for t in np.linspace(0.0, setting.t_final, f["knots"])) if f.get("knots") else ()
        )
        try:
            return GainFamily(
                setting.ctrl.m,
                setting.ctrl.relative_degree,
                f.get("shared", True),
                tuple(f.get("frozen", ())),
                f.get("parameterization", "damping"),
                knots,
                f.get("min_damping", 0.0),
            )
        except ValueError as err:
            raise ProblemError(f"[tune.family]: {err}") from None

    def as_dict(self) -> dict:
        """Plain JSON (a summary's ``tune`` block; :func:`read` reads it back)."""
        out = {"seed": self.seed, "steps": self.steps, "family": dict(self.family)}
        for k in ("loss", "scenarios", "optimizer", "stopping", "baselines"):
            out[k] = getattr(self, k)._asdict()
        if self.requirement is not None:
            out["requirement"] = self.requirement._asdict()
        return out


FAMILY_KEYS = ("parameterization", "shared", "knots", "knot_times", "min_damping", "frozen")


def read_section(data: dict) -> TuneSettings:
    """The :class:`TuneSettings` of a problem's data (its ``[tune]`` and ``[certify]`` sections):
    the schema :data:`wmrjax.problem.JOB_SECTIONS` validates at load."""
    return read(data.get("tune", {}), data.get("certify", {}))


def read(tune: dict, certify: dict | None = None) -> TuneSettings:
    """The :class:`TuneSettings` of a ``[tune]`` section (a dict), checked key by key
    (``certify``: the problem's ``[certify]`` section, whose eps a requirement defaults to)."""
    check_keys(
        "tune",
        tune,
        ("seed", "steps", "family", "loss", "scenarios", "optimizer", "stopping", "baselines", "requirement"),
    )
    seed = integer("tune", "seed", tune.get("seed", 0), 0, 2**32 - 1)
    steps = integer("tune", "steps", tune.get("steps", 40), 1)
    family = _family(tune.get("family", {}))
    loss = LossWeights(**_floats("tune.loss", tune.get("loss", {}), LossWeights._fields, nonnegative))
    try:
        loss.check()
    except ValueError as err:
        raise ProblemError(f"[tune.loss]: {err}") from None
    sc = tune.get("scenarios", {})
    check_keys("tune.scenarios", sc, Scenarios._fields)
    scenarios = Scenarios(
        *(
            integer("tune.scenarios", k, sc.get(k, getattr(Scenarios(), k)), 1)
            for k in ("train", "validation", "heldout")
        ),
        _bool("tune.scenarios", "resample", sc.get("resample", False)),
        nonnegative("tune.scenarios", "mismatch", sc.get("mismatch", 0.1)),
    )
    if not scenarios.mismatch < 1:
        raise ProblemError(f"[tune.scenarios] mismatch: expected a number in [0, 1), got {scenarios.mismatch}")
    opt = Optimizer(**_floats("tune.optimizer", tune.get("optimizer", {}), Optimizer._fields, positive))
    if not opt.decay_to <= 1:
        raise ProblemError(f"[tune.optimizer] decay_to: expected a number in (0, 1], got {opt.decay_to}")
    st = tune.get("stopping", {})
    check_keys("tune.stopping", st, Stopping._fields)
    stopping = Stopping(*(integer("tune.stopping", k, st.get(k, getattr(Stopping(), k)), 1) for k in Stopping._fields))
    baselines = _baselines(tune.get("baselines", {}))
    requirement = certified.read(tune.get("requirement"), certify or {})
    return TuneSettings(family, loss, scenarios, opt, stopping, baselines, steps, seed, requirement)


def _floats(section, table, fields, check) -> dict:
    check_keys(section, table, fields)
    return {k: check(section, k, v) for k, v in table.items()}


def _bool(section, key, v) -> bool:
    if not isinstance(v, bool):
        raise ProblemError(f"[{section}] {key}: expected true or false, got {v!r}")
    return v


def _family(f: dict) -> dict:
    check_keys("tune.family", f, FAMILY_KEYS)
    out = {}
    if "parameterization" in f:
        if f["parameterization"] not in ("damping", "poles"):
            raise ProblemError(
                f'[tune.family] parameterization: expected "damping" or "poles", got {f["parameterization"]!r}'
            )
        out["parameterization"] = f["parameterization"]
    if "shared" in f:
        out["shared"] = _bool("tune.family", "shared", f["shared"])
    if "knots" in f:
        k = integer("tune.family", "knots", f["knots"], 0)
        if k == 1:
            raise ProblemError("[tune.family] knots: a gain schedule needs at least 2 knots (0: constant gains)")
        out["knots"] = k
    if "knot_times" in f:
        kt = f["knot_times"]
        if not (
            isinstance(kt, list)
            and len(kt) >= 2
            and all(isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t >= 0 for t in kt)
            and all(b > a for a, b in zip(kt, kt[1:]))
        ):
            raise ProblemError(
                f"[tune.family] knot_times: expected >= 2 strictly increasing times >= 0 [s], got {kt!r}"
            )
        out["knot_times"] = [float(t) for t in kt]
    if "min_damping" in f:
        md = nonnegative("tune.family", "min_damping", f["min_damping"])
        if not md < 1:
            raise ProblemError(f"[tune.family] min_damping: expected a number in [0, 1), got {md}")
        out["min_damping"] = md
    if "frozen" in f:
        fr = f["frozen"]
        if not (isinstance(fr, list) and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in fr)):
            raise ProblemError(f"[tune.family] frozen: expected a list of parameter indices >= 0, got {fr!r}")
        out["frozen"] = list(fr)
    return out


def _baselines(b: dict) -> Baselines:
    check_keys("tune.baselines", b, Baselines._fields)
    d = Baselines()
    out = Baselines(
        integer("tune.baselines", "seeds", b.get("seeds", d.seeds), 1),
        positive("tune.baselines", "budget", b.get("budget", d.budget)),
        integer("tune.baselines", "cma_population", b.get("cma_population", d.cma_population), 0),
        positive("tune.baselines", "cma_sigma", b.get("cma_sigma", d.cma_sigma)),
        positive("tune.baselines", "search_low", b.get("search_low", d.search_low)),
        positive("tune.baselines", "search_high", b.get("search_high", d.search_high)),
    )
    if out.cma_population == 1:
        raise ProblemError(
            "[tune.baselines] cma_population: CMA-ES ranks its candidates, expected >= 2 (0: its default)"
        )
    if not out.search_low < out.search_high:
        raise ProblemError(f"[tune.baselines]: need search_low < search_high, got {out.search_low}, {out.search_high}")
    return out
