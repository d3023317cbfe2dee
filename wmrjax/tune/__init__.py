"""Gain tuning by gradient descent through the simulator (optax): ``wmrjax tune``.

* :mod:`wmrjax.tune.config` -- a run's settings in small groups (the ``[tune]`` section of a problem file);
* :mod:`wmrjax.tune.gains` -- the gain family: poles from unconstrained parameters (softplus),
  shared or per output, frozen entries, gain schedules;
* :mod:`wmrjax.tune.losses` -- the loss terms of a :class:`wmrjax.Trajectory` and their weights;
* :mod:`wmrjax.tune.scenarios` -- scenarios drawn from a problem, and their rollouts;
* :mod:`wmrjax.tune.loop` -- :func:`tune`: an optax optimizer through the runs, with held-out early
  stopping and JSON checkpoints;
* :mod:`wmrjax.tune.baselines` -- random search and CMA-ES on the same objective.

Example::

    problem = wmrjax.problem.Problem.load("wmrjax/examples/section_6_1_plant.toml")
    setting = problem.setting("tuning")
    settings = wmrjax.tune.config.read(problem.section("tune"))
    result = wmrjax.tune.tune(setting, settings.gain_family(setting), optax.adam(0.1), steps=40)
"""

from wmrjax.examples import PROBLEMS, problem_file
from wmrjax.tune.baselines import BaselineRun, cma_es, random_search
from wmrjax.tune.config import Baselines, Optimizer, Scenarios, Stopping, TuneSettings
from wmrjax.tune.gains import GainFamily
from wmrjax.tune.loop import Context, TuneResult, mean_loss, mean_loss_and_grad, objective, tune
from wmrjax.tune.losses import LossWeights, Metrics, metrics
from wmrjax.tune.scenarios import Scenario, rollout

__all__ = [
    "PROBLEMS",
    "problem_file",
    "BaselineRun",
    "cma_es",
    "random_search",
    "Baselines",
    "Optimizer",
    "Scenarios",
    "Stopping",
    "TuneSettings",
    "GainFamily",
    "Context",
    "TuneResult",
    "mean_loss",
    "mean_loss_and_grad",
    "objective",
    "tune",
    "LossWeights",
    "Metrics",
    "metrics",
    "Scenario",
    "rollout",
]
