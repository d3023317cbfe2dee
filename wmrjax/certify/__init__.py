r"""Certification: from which initial errors the dynamic linearizing law provably stays away
from its singular set (paper §6, Lemma 2, Remark 16, Lemma 3, eqs 50-65), and how tight that is.

Every radius-producing function (:func:`lemma2`, :func:`exact_map_radius`,
:func:`empirical_radius`, :func:`falsified_radius`, :func:`analyse`) is ``(ctrl, params, *,
t_final, eps, ...)``, and the rollout helpers (:func:`verify`, :func:`min_distance`,
:func:`falsify`) are ``(ctrl, params, *, t_final, ...)``: the closed loop first, everything
else keyword-only; each returns a NamedTuple with fixed fields:

* :mod:`~wmrjax.certify.lemma2` -- M1 (closed form for every type, and Remark 16's local
  search), K2 three ways (eq 64, an automatic Lyapunov bound, the exact ||e^{At}||), F and
  the certified radius :math:`\min_t F(t)`: :func:`lemma2`;
* :mod:`~wmrjax.certify.exact_map` -- the exact-map radius from
  :math:`\tilde\zeta(t) = e^{At}\tilde\zeta(0)`: closed form per time for the linear
  singular sets, branch and bound with a proved lower bound for (1,2)'s curved one;
* :mod:`~wmrjax.certify.empirical` -- batch rollouts: (53) and regularity inside a ball,
  distances to the singular set, the empirical radius per direction;
* :mod:`~wmrjax.certify.falsify` -- falsification (an upper bound): instantaneous, sampling
  and gradient stages, failures confirmed on a finer simulation;
* :mod:`~wmrjax.certify.pipeline` -- :func:`analyse`, all of the above in one report;
* :mod:`~wmrjax.certify.budget` -- what :func:`analyse` will cost (measured step cost, rollouts
  per stage, memory), said before it runs, and its counts sized to a time budget;
* :mod:`~wmrjax.certify.saturation` -- the saturation-free radius (proved by affine
  enclosures, :mod:`~wmrjax.certify.affine` over :mod:`~wmrjax.certify.interval`): inside it a
  saturating plant's loop is the nominal one;
* :mod:`~wmrjax.certify.deviation` -- the mismatch radius (proved): the real loop's deviation
  from the nominal one under input-scale and geometry ranges, a digital controller's zero-order
  hold and bounded measurement noise, bounded through the exact error map, and the radius it
  leaves (velocity level);
* :mod:`~wmrjax.certify.reach` -- a digital controller's loop (hold, noise, limits,
  scales) enclosed period by period from a ball of initial errors: its proved radius;
* :mod:`~wmrjax.certify.worst_noise` -- the measurement noise within that bound that brings a
  run closest to the singular set (projected gradient: estimated, for the falsifier);
* :mod:`~wmrjax.certify.real_loop` -- what each radius covers (:class:`Feature`, :class:`Kind`)
  and the problem's own loop (limits, a digital controller, mismatch, noise): its falsified
  radius and the problem's certificate (:func:`problem_certificate`).

Every radius above but the real loop's, the saturation-free and the mismatch ones is the *nominal continuous*
loop's.

Only dynamic linearizing laws are certified: a static law raises ``ValueError``.
"""

from wmrjax.certify.budget import Counts, WorkEstimate, plan, scaled, step_cost
from wmrjax.certify.deviation import (
    Mismatch,
    MismatchRadius,
    deviation_rate,
    hold_rate,
    mismatch_radius,
    sampled_inputs,
)
from wmrjax.certify.empirical import (
    CONFIRM_BLOCK,
    CONFIRM_DT_FACTOR,
    Distances,
    EmpiricalRadius,
    Verification,
    empirical_radius,
    min_distance,
    sample_sphere,
    verify,
    verify_all,
)
from wmrjax.certify.exact_map import (
    ExactMapRadius,
    Slice,
    curved_exact_map_radius,
    differentiable_exact_map_radius,
    exact_map_radius,
    min_norm_to_ball,
    singular_rows,
    slice_basis,
)
from wmrjax.certify.falsify import Falsification, FalsifiedRadius, falsified_radius, falsify
from wmrjax.certify.lemma2 import (
    Certificate,
    Lemma2Report,
    LyapunovBound,
    certificate,
    check_lemma2_args,
    k2_exact,
    k2_lyapunov,
    k2_paper,
    k2_transition,
    lemma2,
    lyapunov_bound,
    m1_closed_form,
    m1_numerical,
    transition_steps,
)
from wmrjax.certify.pipeline import CertificationReport, EmpiricalCheck, analyse, plain
from wmrjax.certify.reach import (
    HeldReach,
    HeldReachRadius,
    SingularDistance,
    Uncertainty,
    held_reach,
    held_reach_radius,
    sample_jets,
)
from wmrjax.certify.real_loop import (
    Feature,
    Kind,
    RealLoopFalsified,
    inert_features,
    planned_runs,
    plant_features,
    plant_range,
    problem_certificate,
    radius_labels,
    real_loop_distances,
    real_loop_falsified_radius,
)
from wmrjax.certify.saturation import SaturationFreeRadius, saturation_free_radius
from wmrjax.certify.worst_noise import WorstNoise, worst_noise

__all__ = [
    "Counts",
    "WorkEstimate",
    "plan",
    "scaled",
    "step_cost",
    "Mismatch",
    "MismatchRadius",
    "deviation_rate",
    "hold_rate",
    "mismatch_radius",
    "sampled_inputs",
    "CONFIRM_BLOCK",
    "CONFIRM_DT_FACTOR",
    "Distances",
    "EmpiricalRadius",
    "Verification",
    "empirical_radius",
    "min_distance",
    "sample_sphere",
    "verify",
    "verify_all",
    "ExactMapRadius",
    "Slice",
    "curved_exact_map_radius",
    "differentiable_exact_map_radius",
    "exact_map_radius",
    "min_norm_to_ball",
    "singular_rows",
    "slice_basis",
    "Falsification",
    "FalsifiedRadius",
    "falsified_radius",
    "falsify",
    "Certificate",
    "Lemma2Report",
    "LyapunovBound",
    "certificate",
    "check_lemma2_args",
    "k2_exact",
    "k2_lyapunov",
    "k2_paper",
    "k2_transition",
    "lemma2",
    "lyapunov_bound",
    "m1_closed_form",
    "m1_numerical",
    "transition_steps",
    "CertificationReport",
    "EmpiricalCheck",
    "analyse",
    "plain",
    "Feature",
    "Kind",
    "RealLoopFalsified",
    "inert_features",
    "planned_runs",
    "plant_features",
    "plant_range",
    "problem_certificate",
    "radius_labels",
    "real_loop_distances",
    "real_loop_falsified_radius",
    "HeldReach",
    "HeldReachRadius",
    "SingularDistance",
    "Uncertainty",
    "held_reach",
    "held_reach_radius",
    "sample_jets",
    "SaturationFreeRadius",
    "saturation_free_radius",
    "WorstNoise",
    "worst_noise",
]
