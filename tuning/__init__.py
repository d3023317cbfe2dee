"""Gain tuning by gradient descent through the simulator (optax): ``python -m tuning``.

* :mod:`tuning.config` -- a run's settings in small groups (the ``[tune]`` section of a problem file);
* :mod:`tuning.gains` -- the gain family: poles from unconstrained parameters (softplus),
  shared or per output, frozen entries, gain schedules;
* :mod:`tuning.losses` -- the loss terms of a :class:`wmrjax.Trajectory` and their weights;
* :mod:`tuning.scenarios` -- scenarios drawn from a problem, and their rollouts;
* :mod:`tuning.loop` -- :func:`tune`: an optax optimizer through the runs, with held-out early
  stopping and JSON checkpoints;
* :mod:`tuning.baselines` -- random search and CMA-ES on the same objective.

Example::

    problem = wmrjax.problem.Problem.load("tuning/problems/section_6_1.toml")
    setting = problem.setting("tuning")
    settings = tuning.config.read(problem.section("tune"))
    result = tuning.tune(setting, settings.gain_spec(setting), optax.adam(0.1), steps=40)
"""

from tuning.baselines import BaselineRun, cma_es, random_search  # noqa: F401
from tuning.config import Baselines, Optimizer, Scenarios, Stopping, TuneSettings  # noqa: F401
from tuning.gains import GainSpec  # noqa: F401
from tuning.loop import Context, TuneResult, mean_loss, mean_loss_and_grad, objective, tune  # noqa: F401
from tuning.losses import LossWeights, Metrics, metrics  # noqa: F401
from tuning.problems import PROBLEMS, problem_file  # noqa: F401
from tuning.scenarios import Scenario, rollout  # noqa: F401

GainFamily = GainSpec
"""The family of tuned gains (another name for :class:`GainSpec`)."""
