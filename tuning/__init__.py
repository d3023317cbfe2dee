"""Gain tuning by gradient descent through the simulator (optax): ``python -m tuning``.

* :mod:`tuning.gains` — poles from unconstrained parameters (softplus), shared or per
  axis, frozen entries;
* :mod:`tuning.losses` — tracking, effort, saturation, singularity-barrier and certificate terms;
* :mod:`tuning.scenarios` — scenario batches (initial conditions, references, mismatch,
  actuator limits, sensor noise) and the sampled-data rollout;
* :mod:`tuning.loop` — the optax loop with held-out early stopping, JSON checkpoints and
  the random-search baseline.
"""

from tuning.gains import GainSpec  # noqa: F401
from tuning.losses import LossWeights, Metrics  # noqa: F401
from tuning.baselines import BaselineRun, cma_es, random_search  # noqa: F401
from tuning.loop import TuneConfig, batch_value, batch_value_and_grad, build, objective, tune  # noqa: F401
from tuning.problems import PROBLEMS, preset  # noqa: F401
from tuning.scenarios import RolloutConfig, Scenario, rollout  # noqa: F401
