r"""Named tuning problems: ``python -m tuning --problem NAME``.

* ``section_6_1`` (default): the §6.1 robot ((2,0), e = 0, reference (62)), dynamic law at
  velocity level, (omega, zeta) shared by both outputs: 2 parameters.
* ``car_schedule``: the (1,1) car (L = 1 m, e = 0.3 m), dynamic law at velocity level
  (relative degree 3), random smooth references (speed >= 0.5 m/s: with e = 0.3 m the output
  point of a slower reference can stop on a sharp turn, where the law is singular), initial
  errors +-0.3 m and +-0.1 m/s, +-10 % mismatch, actuator limits (|eta1| <= 2 m/s,
  |zeta1| <= 1.5 rad/s), sensor noise, 20 Hz hold; a gain schedule :math:`\Lambda(t)` with 4
  knots on [0, 10] s, per output (omega, zeta, lambda): 24 parameters.
* ``torque_2_1``: type (2,1) (outputs x, y, theta) at torque level (Lemma 1, relative degree
  3) feeding back measured wheel velocities, random smooth references with a 0.3 rad crab
  angle, +-10 % torque and geometry mismatch, torque limits, noise; per output the outer
  loop's (omega, zeta) and the inner loop's pole lambda: 9 parameters.

Both new problems draw fresh training scenarios at every gradient step (``resample``): on a
fixed set of 32 the tuned gains fitted it and met saturation and near-singular events on
unseen scenarios (held-out loss above the paper gains' on some seeds). The baselines search
the fixed training set, and every method's training objective is reported on it. Baselines
get 4x the gradient's rollouts. Every field not set here is :class:`tuning.TuneConfig`'s default.
"""

from __future__ import annotations

PROBLEMS: dict[str, dict] = {
    "section_6_1": {},
    "car_schedule": dict(
        robot="(1,1)", task="posture", level="velocity", reference="random", geometry=(1.0, 0.3, 0.0),
        knots=4, shared=False, n_train=32, n_validation=32, n_heldout=64, steps=60, learning_rate=0.1,
        patience=8, input_limit=(2.0, 1.5), noise_std=(0.01, 0.01, 0.005, 0.005), mismatch=0.1,
        ic_position=0.3, ic_velocity=0.1, ref_min_speed=0.5, resample=True, baseline_budget=4.0),
    "torque_2_1": dict(
        robot="(2,1)", task="posture", level="torque", reference="random", heading_offset=0.3,
        shared=False, n_train=32, n_validation=32, n_heldout=64, steps=80, learning_rate=0.1, patience=8,
        input_limit=(3.0, 3.0, 3.0), noise_std=(0.01, 0.01, 0.005, 0.005), mismatch=0.1,
        ic_position=0.5, ic_velocity=0.3, resample=True, baseline_budget=4.0),
}


def preset(name: str, **overrides):
    """The :class:`tuning.TuneConfig` of a named problem, with ``overrides`` applied (checked).

    Raises:
      ValueError: an unknown problem name or a bad override.
    """
    from tuning.loop import TuneConfig

    if name not in PROBLEMS:
        raise ValueError(f"problem must be one of {sorted(PROBLEMS)}, got {name!r}")
    return TuneConfig(**{**PROBLEMS[name], "problem": name, **overrides}).check()
