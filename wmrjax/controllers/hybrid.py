r"""Hybrid parking of a type (2,0) robot (paper §6.2): dynamic linearization along a reference
that ends at rest, then a time-varying stabilizer near the goal.

The dynamic linearizing law (Table 4, eq 39) is singular where the robot stops
(:math:`\chi_1 = 0`), so it cannot bring the robot to rest. Brockett's condition rules out
continuous static stabilizers; the paper switches, once the robot enters the disk
:math:`x^2 + y^2 \le r_s^2` (printed: :math:`x^2 + y^2 = \sqrt2/10`), to the time-periodic
law "CL3 of Pomet et al. (1992) with :math:`\lambda = 40`, :math:`\psi(\theta) = \theta`".

**Reconstruction.** The text of CL3 was not available; :func:`stabilizer` implements the
reconstruction documented in ``errata.md`` (the Pomet-type time-varying law for the
unicycle as used in public course code citing Pomet et al. 1992). With
:math:`\tau = t - t_{switch}`, target the origin, e = 0:

.. math::
   \eta_1 = x\sin\theta - y\cos\theta,\qquad
   \psi'(\theta)\,\eta_2 = -\psi(\theta) - \lambda(x\cos\tau + \dot x\cos\tau - x\sin\tau),
   \quad \dot x = -\eta_1\sin\theta,

so that :math:`z = \psi(\theta) + \lambda x\cos\tau` obeys :math:`\dot z = -z` and
:math:`\tfrac{d}{dt}\tfrac12(x^2+y^2) = -\eta_1^2 \le 0` (LaSalle for periodic systems:
convergence, not exponential).

The hybrid closed loop is one :func:`wmrjax.simulate`-able system. Its state is a
:class:`HybridState` pytree with named fields: the tracking state ``(x, y, theta, chi1)``,
an integer ``mode`` (:data:`TRACKING` or :data:`PARKING`), ``t_switch`` and the state at the switch;
all but the tracking state are discrete (zero derivative) and change only in
:meth:`Hybrid.post_step`, the discrete transition applied after every RK4 step: the switch happens at the first step whose end
state is inside the disk, never earlier. At the switch theta is replaced by its
representative nearest 0 (:math:`\psi(\theta) = \theta` is not 2 pi periodic) and never
wrapped again. No Python branching on values: it jits and vmaps. After the switch the
linearizing law is evaluated at a harmless state (chi1 = 1) and discarded by ``where``, so
neither values nor gradients of the singular branch leak.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math, robots
from wmrjax._validate import concrete
from wmrjax.controllers.dynamic import DynamicLinearization, DynamicParams, dynamic_linearization
from wmrjax.controllers.law import Aux, Level
from wmrjax.references import Reference
from wmrjax.robots import Geometry
from wmrjax.system import ClosedLoop

PAPER_R_SWITCH = float(np.sqrt(np.sqrt(2.0) / 10.0))  # x^2 + y^2 = sqrt(2)/10  ->  r_s = 0.376 m
PAPER_LAMBDA = 40.0
TRACKING, PARKING = 0, 1  # values of HybridState.mode


def identity(theta):
    """psi(theta) = theta, the paper's choice."""
    return theta


def stabilizer(X, tau, lam, psi: Callable = identity):
    r"""The time-varying parking law (reconstruction of CL3, see module docstring).

    Args:
      X: (3,) posture (x, y, theta) of a type (2,0) robot with e = 0 [m, m, rad]; theta
        is used as is (pick its representative before calling).
      tau: time since the switch [s].
      lam: gain lambda > 0.
      psi: a function with psi(0) = 0 and psi' > 0 (default the identity).

    Returns:
      (2,) velocity input (eta1 [m/s], eta2 [rad/s]).
    """
    x, y, th = X[0], X[1], X[2]
    s, c = _math.sincos(th)
    st, ct = _math.sincos(tau)
    eta1 = x * s - y * c
    xdot = -eta1 * s
    p, dp = jax.jvp(psi, (th,), (jnp.ones_like(th),))
    eta2 = (-p - lam * (x * ct + xdot * ct - x * st)) / dp
    return jnp.stack([eta1, eta2])


class StabilizerParams(NamedTuple):
    """Parameters of the stand-alone stabilizer (a pytree)."""

    lam: jnp.ndarray  # lambda > 0
    t_switch: jnp.ndarray  # its clock starts here [s]


@dataclasses.dataclass(frozen=True)
class TimeVarying(ClosedLoop):
    """The stabilizer alone as a closed loop on (x, y, theta) (for :func:`wmrjax.simulate`)."""

    psi: Callable = identity
    n_state: int = 3
    state_names: tuple = ("x", "y", "theta")

    def vector_field(self, t, z, params: StabilizerParams):
        """The stabilizer's closed loop on the (2,0) kinematics: ``(zdot, Aux)`` at time ``t`` [s]."""
        u = stabilizer(z, t - params.t_switch, params.lam, self.psi)
        zdot = robots.kinematic(robots.TYPES["(2,0)"], z, u, Geometry(e=0.0))
        return zdot, Aux(u, jnp.ones_like(z[0]))

    def params(self, lam=PAPER_LAMBDA, t_switch=0.0) -> StabilizerParams:
        """The stabilizer's parameters: gain ``lam`` (> 0) and the switching time ``t_switch`` [s]."""
        check_stabilizer_args(lam)
        return StabilizerParams(jnp.asarray(lam, float), jnp.asarray(t_switch, float))


def check_stabilizer_args(lam, r_switch=None) -> None:
    """ValueError unless ``lam`` (and ``r_switch``, where given) are finite and > 0."""
    lv = concrete(lam)
    if lv is not None and not (np.all(np.isfinite(lv)) and np.all(np.asarray(lv) > 0)):
        raise ValueError(f"lambda (the stabilizer gain) must be > 0, got {lam!r}")
    if r_switch is not None:
        rv = concrete(r_switch)
        if rv is not None and not (np.all(np.isfinite(rv)) and np.all(np.asarray(rv) > 0)):
            raise ValueError(f"the switching radius r_s must be > 0 [m], got {r_switch!r}")


class HybridParams(NamedTuple):
    """Everything array-valued the hybrid loop depends on (a pytree)."""

    tracking: DynamicParams  # gains, reference, geometry (e = 0)
    r_switch: jnp.ndarray  # switching radius r_s [m]
    lam: jnp.ndarray  # stabilizer gain


class HybridState(NamedTuple):
    """State of the hybrid loop (a pytree; :func:`wmrjax.simulate` flattens it internally).

    Attributes:
      tracking: (4,) ``(x, y, theta, chi1)`` [m, m, rad, m/s]; after the switch theta is the
        representative nearest 0 (never wrapped again) and chi1 is frozen.
      mode: integer scalar, :data:`TRACKING` (0) or :data:`PARKING` (1).
      t_switch: time of the switch [s] (0 before it).
      at_switch: (4,) ``(x, y, theta, chi1)`` recorded at the switch (zeros before it).
    """

    tracking: jnp.ndarray
    mode: jnp.ndarray
    t_switch: jnp.ndarray
    at_switch: jnp.ndarray

    @property
    def switched(self):
        """True once the loop has switched to parking (the stabilizer)."""
        return self.mode == PARKING


@dataclasses.dataclass(frozen=True)
class Hybrid(ClosedLoop):
    """Dynamic linearization, then the time-varying stabilizer (paper §6.2), for type (2,0), e = 0.

    State :class:`HybridState`: the discrete fields change only at the switch
    (:meth:`post_step`), so every run's final state records when and where it switched.
    """

    psi: Callable = identity
    tracking: DynamicLinearization = dataclasses.field(
        default_factory=lambda: dynamic_linearization("(2,0)", Level.VELOCITY)
    )

    n_state = 10
    state_names = ("x", "y", "theta", "chi1", "mode", "t_switch", "x_switch", "y_switch", "theta_switch", "chi1_switch")

    def vector_field(self, t, z: HybridState, params: HybridParams):
        """The hybrid loop's field: tracking, or parking after the switch; ``(zdot, Aux)``."""
        parking = z.mode == PARKING
        zt = z.tracking
        # the linearizing branch sees a regular state after the switch: no inf/NaN in values or grads
        zt_safe = jnp.where(parking, zt.at[3].set(1.0), zt)
        zdot_t, aux_t = self.tracking.vector_field(t, zt_safe, params.tracking)
        u_p = stabilizer(zt[:3], t - z.t_switch, params.lam, self.psi)
        u = jnp.where(parking, u_p, aux_t.control)
        Xdot = robots.kinematic(robots.TYPES["(2,0)"], zt[:3], u, Geometry(e=0.0))
        chi_dot = jnp.where(parking, 0.0, zdot_t[3])
        zdot = HybridState(
            jnp.concatenate([Xdot, chi_dot[None]]),
            jnp.zeros_like(z.mode),
            jnp.zeros_like(z.t_switch),
            jnp.zeros_like(z.at_switch),
        )
        margin = jnp.where(parking, jnp.ones_like(aux_t.margin), aux_t.margin)
        regularity = jnp.where(parking, jnp.nan, aux_t.regularity)  # no singular set while parking
        return zdot, Aux(u, margin, regularity)  # applied (eta1, eta2); |chi1| while tracking, 1 while parking

    def check_run(self, params, *, t0, dt, n_steps: int) -> None:
        """Before compiling: hybrid parameters, and a step that is stable for the tracking phase."""
        del t0, n_steps
        if not isinstance(params, HybridParams):
            raise ValueError(
                f"params must be HybridParams (build them with hybrid_parking().params), got {type(params).__name__}"
            )
        self.tracking.check_params(params.tracking)
        self.tracking.check_step(params.tracking, dt)

    def post_step(self, t, z: HybridState, params: HybridParams) -> HybridState:
        """Discrete transition at the end of a step: switch when inside the disk (once)."""
        zt = z.tracking
        inside = zt[0] ** 2 + zt[1] ** 2 <= params.r_switch**2
        switch = (z.mode == TRACKING) & inside
        zt = zt.at[2].set(jnp.where(switch, _math.wrap_angle(zt[2]), zt[2]))
        return HybridState(
            zt,
            jnp.where(switch, PARKING, z.mode).astype(z.mode.dtype),
            jnp.where(switch, t, z.t_switch),
            jnp.where(switch, zt, z.at_switch),
        )

    def params(
        self, reference: Reference, poles=1.0, r_switch=PAPER_R_SWITCH, lam=PAPER_LAMBDA, t_end: float = 10.0
    ) -> HybridParams:
        """Build and validate :class:`HybridParams`.

        Args:
          reference: must end (at ``t_end``) inside the switching disk.
          poles: closed-loop poles of the tracking phase (eq 49).
          r_switch: switching radius [m] (paper: x^2 + y^2 = sqrt(2)/10).
          lam: stabilizer gain (paper: 40).
          t_end: time [s] at which the reference comes to rest.

        Raises:
          ValueError: r_switch <= 0, lam <= 0, or a reference whose end point is outside the disk.
        """
        check_stabilizer_args(lam, r_switch)
        tp = self.tracking.params(reference, poles, Geometry(e=0.0))
        end = np.asarray(reference.position(jnp.asarray(float(t_end))))
        if not np.hypot(*end) < float(r_switch):
            raise ValueError(
                f"the reference must end inside the switching disk: at t_end = {t_end} s it is at "
                f"({end[0]:.3g}, {end[1]:.3g}) m, |p| = {np.hypot(*end):.3g} m >= r_s = {float(r_switch):.3g} m"
            )
        return HybridParams(tp, jnp.asarray(r_switch, float), jnp.asarray(lam, float))

    def initial_state(self, zeta0, params: HybridParams) -> HybridState:
        """From an initial output jet ((x, y), (xdot, ydot)) via Lemma 3's Psi^-1; mode TRACKING."""
        z = self.tracking.initial_state(zeta0, params.tracking)
        zero = jnp.zeros((), z.dtype)
        return HybridState(z, jnp.asarray(TRACKING, dtype=jnp.int32), zero, jnp.zeros(4, z.dtype))


def hybrid_parking(psi: Callable = identity) -> Hybrid:
    """The §6.2 hybrid closed loop (type (2,0), e = 0, velocity level)."""
    return Hybrid(psi=psi)
