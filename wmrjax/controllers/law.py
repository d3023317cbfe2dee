r"""What every linearizing controller shares: the closed-loop protocol and one law.

* :class:`~wmrjax.system.ClosedLoop` (:mod:`wmrjax.system`) is what :func:`wmrjax.simulate`
  runs; :class:`LinearizingController` is one.
* :class:`Extension` is the mechanics of one table row at velocity level: the outputs, the
  compensator states that delay some input combinations, and how the new inputs U drive
  the plant (Table 4). A static law (Table 3) is the same with no compensator and U = u.
* :class:`LinearizingLaw` derives everything else from an extension and a level by the
  generic engine of :mod:`wmrjax.linearize`: the diffeomorphism :math:`\zeta = \Psi(X_e)`
  (eq 35), the decoupling matrix and drift, and the auxiliary law (49) with the errata sign,
  at velocity level (kinematic model 5) and at torque level (model 8) by the cascade of
  Lemma 1: the torque-level state appends the velocity-level new inputs U and takes
  :math:`V = \dot U` as input, with the same outputs, relative degrees one higher and the
  same decoupling matrix.

:class:`wmrjax.controllers.DynamicLinearization` and
:class:`wmrjax.controllers.StaticLinearization` are siblings that each hold a law (by
composition) plus their table's per-type facts.

State ``z`` of a law (unbatched vector): ``(X, c)`` at velocity level, ``(X, c, U)`` at
torque level; the plant input is ``u = plant_input(X, c, U)`` (velocity level) or
:math:`v = \dot u` along the flow (torque level).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
import warnings
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import core as jax_core  # trace_state_clean: whether a call happens inside a trace

from wmrjax import _math, linearize, resources, robots
from wmrjax._validate import check_finite, check_real, check_shape, concrete, is_concrete
from wmrjax.gains import Gains, GainSchedule
from wmrjax.references import Reference, check_domain, spline_degree_for
from wmrjax.resources import REFERENCE_GRID_STEP
from wmrjax.robots import Geometry, RobotType
from wmrjax.system import ClosedLoop

# |det K| below this is treated as singular inside the law (the division is clamped);
# runs report the true margin so such events are flagged.
DET_FLOOR = 1e-12


class Level(enum.StrEnum):
    """The model the law commands: velocities (kinematic model 5) or torques (Lemma 1, model 8).

    A string enumeration: ``Level.TORQUE == "torque"`` and they hash alike, so problem files,
    command-line options and JSON outputs keep the plain names; the code compares members.
    """

    VELOCITY = "velocity"
    TORQUE = "torque"


class Task(enum.StrEnum):
    """What a law tracks: the whole posture (dynamic laws; (3,0) by Prop 3), or a point of the
    robot (Table 3's static laws). A string enumeration, like :class:`Level`."""

    POSTURE = "posture"
    POINT = "point"


def check_level(level) -> Level:
    """``level`` (a :class:`Level` or its name) as a :class:`Level`; ValueError otherwise."""
    try:
        return Level(level)
    except (ValueError, TypeError):
        raise ValueError(f"level must be one of {tuple(str(lv) for lv in Level)}, got {level!r}") from None


class Aux(NamedTuple):
    """What a closed-loop evaluation reports besides the state derivative.

    Attributes:
      control: plant input: u (velocity level) or v (torque level).
      margin: singularity margin, >= 0 (``|det K|`` for the linearizing laws; Remark 14).
      regularity: optional signed regularity function whose zero set is the singular set
        (``det K`` for the linearizing laws), so that ``margin = |regularity|``; a change of
        its sign between two evaluations of a run is a crossing of the singular set
        (:func:`wmrjax.simulate` flags it however large the sampled margins are). NaN (or
        None) where the system has no singular set at that point.
    """

    control: jnp.ndarray
    margin: jnp.ndarray
    regularity: Any = None


# --- geometry requirements (keyword facts of the table rows) -------------------------------


@dataclasses.dataclass(frozen=True)
class Requirement:
    """A condition on one geometry constant, for the rows' regularity conditions.

    Attributes:
      field: "L", "e" or "delta".
      test: "nonzero" (value != 0) or "sin_nonzero" (value != k pi).
      why: the table's words, for the error message.
    """

    field: str
    test: str
    why: str

    def violated(self, g: Geometry) -> bool:
        """True where the geometry breaks this requirement (False for a traced value)."""
        v = concrete(getattr(g, self.field))
        if v is None:
            return False
        v = float(v)
        return v == 0.0 if self.test == "nonzero" else abs(math.sin(v)) < 1e-12


def check_requirements(requirements, g: Geometry, where: str) -> None:
    """ValueError naming the first requirement the (concrete) geometry violates."""
    for req in requirements:
        if req.violated(g):
            what = "!= 0" if req.test == "nonzero" else "!= k pi"
            raise ValueError(
                f"{where}: geometry.{req.field} must be {what} ({req.why}); "
                f"got {req.field} = {float(getattr(g, req.field))!r}"
            )


# --- the mechanics of a table row -----------------------------------------------------------


def _identity_input(X, c, U, g):
    return U


def _no_compensator(X, c, U, g):
    return U[:0]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Extension:
    """A row's affine extended system at velocity level (static description).

    Attributes:
      robot: the robot type.
      outputs: ``(X, geometry) -> Y`` linearizing outputs, shape (m,).
      relative_degree: r of every output at velocity level.
      n_comp: number of compensator states c (0: static law).
      comp_names: their names (for reports).
      plant_input: ``(X, c, U, geometry) -> u``, affine in U (identity for a static law).
      compensator: ``(X, c, U, geometry) -> dc/dt``, affine in U.
      angle_outputs: which outputs are angles: their zeroth-order error is wrapped to
        [-pi, pi) (errata: integrate angles unwrapped, wrap only errors).
      extra_margin: optional ``(z, geometry) -> scalar`` multiplying ``|det K|`` in the
        singularity margin, for a singular set that ``|det K|`` alone misses (the (1,1) lever
        L sin(beta) + e cos(beta), errata).
    """

    robot: RobotType
    outputs: Callable = dataclasses.field(repr=False)
    relative_degree: int
    n_comp: int = 0
    comp_names: tuple = ()
    plant_input: Callable = dataclasses.field(default=_identity_input, repr=False)
    compensator: Callable = dataclasses.field(default=_no_compensator, repr=False)
    angle_outputs: tuple = ()
    extra_margin: Callable | None = dataclasses.field(default=None, repr=False)

    @property
    def n_outputs(self) -> int:
        """The number of outputs m (square: one per input)."""
        return self.robot.n_input  # square: m outputs, m new inputs


@dataclasses.dataclass(frozen=True)
class LinearizingLaw:
    """The generic linearizing law of one extension at one level (static, hashable)."""

    extension: Extension
    level: Level

    @property
    def robot(self) -> RobotType:
        """The robot type."""
        return self.extension.robot

    @property
    def m(self) -> int:
        """The number of linearized outputs."""
        return self.extension.n_outputs

    @property
    def relative_degree(self) -> int:
        """The relative degree r of each output (one more at torque level)."""
        return self.extension.relative_degree + (1 if self.level == Level.TORQUE else 0)

    @property
    def n_velocity_state(self) -> int:
        """The velocity-level state's size: the posture and the compensator."""
        return self.robot.n_state + self.extension.n_comp

    @property
    def n_state(self) -> int:
        """The law's state size (with the wheel inputs at torque level)."""
        return self.n_velocity_state + (self.m if self.level == Level.TORQUE else 0)

    @property
    def velocity_level(self) -> "LinearizingLaw":
        """The same law at velocity level."""
        return LinearizingLaw(self.extension, Level.VELOCITY)

    def _velocity_field(self, zv, U, g):
        n = self.robot.n_state
        X, c = zv[:n], zv[n:]
        u = self.extension.plant_input(X, c, U, g)
        xdot = robots.kinematic(self.robot, X, u, g)
        return jnp.concatenate([xdot, self.extension.compensator(X, c, U, g)]) if self.extension.n_comp else xdot

    def field(self, z, U, g):
        """Extended dynamics ``dz/dt = F(z) + G(z) U`` (U: new inputs of this level)."""
        if self.level == Level.VELOCITY:
            return self._velocity_field(z, U, g)
        nv = self.n_velocity_state
        return jnp.concatenate([self._velocity_field(z[:nv], z[nv:], g), U])

    def plant_control(self, z, U, g):
        """The physical input: u (velocity level) or v = du/dt (torque level, by jvp)."""
        n, nv = self.robot.n_state, self.n_velocity_state
        pi = lambda X, c, Uv: self.extension.plant_input(X, c, Uv, g)
        if self.level == Level.VELOCITY:
            return pi(z[:n], z[n:], U)
        zdot = self.field(z, U, g)
        return jax.jvp(pi, (z[:n], z[n:nv], z[nv:]), (zdot[:n], zdot[n:nv], U))[1]

    def lift_measured(self, z, u_measured, g):
        r"""Torque level: the state with its compensator and new inputs corrected to measured
        wheel velocities.

        The plant input :math:`u = \pi(X, c, U)` is affine in :math:`w = (c, U)` for every row of
        Table 4, so the smallest correction :math:`\delta w = J^T (J J^T)^{-1} (u_{meas} - \pi(X, w))`,
        :math:`J = \partial\pi/\partial w`, makes :math:`\pi(X, w + \delta w) = u_{meas}` exactly and
        leaves the entries that u does not determine (e.g. :math:`\dot\chi_1` of (2,0)) as they were.
        With :math:`u_{meas} = \pi(X, c, U)` (nominal conditions) the state is unchanged.

        Args:
          z: torque-level state ``(X, c, U)``.
          u_measured: (n_input,) wheel velocities.
          g: geometry.
        """
        if self.level != Level.TORQUE:
            raise ValueError("lift_measured is for torque-level laws (their state carries the velocities)")
        n, nv = self.robot.n_state, self.n_velocity_state
        X, w = z[:n], z[n:]
        nc = nv - n
        pi = lambda w: self.extension.plant_input(X, w[:nc], w[nc:], g)
        J = _math.jacfwd_small(pi, w)
        # J J^T is m x m (m <= 3): the explicit adjugate keeps the step elementwise (no LAPACK call,
        # which is slow under vmap on CPU and has no counterpart in the exported C step)
        num, det = _math.adjugate_solve(J @ J.T, u_measured - pi(w))
        dw = J.T @ (num / det)
        return jnp.concatenate([X, w + dw])

    def outputs(self, z, g):
        """The linearizing outputs Y, (m,), of state ``z`` with geometry ``g``."""
        return self.extension.outputs(z[: self.robot.n_state], g)

    def jet(self, z, g):
        """``(zeta, a, K)`` of :func:`wmrjax.linearize.output_jet` at ``z``."""
        return linearize.output_jet(
            lambda x, U: self.field(x, U, g), lambda x: self.outputs(x, g), z, self.m, self.relative_degree
        )

    def wrap_error(self, err):
        """Wrap the zeroth-order error of angle outputs to [-pi, pi)."""
        for i in self.extension.angle_outputs:
            err = err.at[0, i].set(_math.wrap_angle(err[0, i]))
        return err

    def regularity_from_det(self, z, det, g):
        """Signed regularity: ``det K`` (times the extension's extra factor); zero on the singular set."""
        if self.extension.extra_margin is not None:
            return det * self.extension.extra_margin(z, g)
        return det

    def margin_from_det(self, z, det, g):
        """Singularity margin from ``det K``: ``|det K|`` (times the extension's extra factor)."""
        return jnp.abs(self.regularity_from_det(z, det, g))

    def margin(self, z, g):
        """Singularity margin at ``z``; 0 on the singular set."""
        return self.margin_from_det(z, jnp.linalg.det(self.jet(z, g)[2]), g)

    def control(self, yref, z, coeffs, g):
        """New input U of the auxiliary law (49, errata sign) and the singularity margin.

        Args:
          yref: (r + 1, m) reference outputs and their derivatives up to order r.
          z: state.
          coeffs: (m, r) Hurwitz coefficients.
          g: geometry.

        Returns:
          ``(U, margin)``; the division by ``det K`` is clamped at :data:`DET_FLOOR`.
        """
        U, reg = self._control(yref, z, coeffs, g)
        return U, jnp.abs(reg)

    def _control(self, yref, z, coeffs, g):
        """``(U, signed regularity)`` of :meth:`control`."""
        zeta, a, K = self.jet(z, g)
        r = self.relative_degree
        err = self.wrap_error(zeta - yref[:r])
        w = yref[r]
        for j in range(r):
            w = w - coeffs[:, j] * err[j]
        num, det = _math.adjugate_solve(K, w - a)
        return num / _math.safe_divisor(det, DET_FLOOR), self.regularity_from_det(z, det, g)

    def closed_loop(self, yref, z, coeffs, g):
        """Closed-loop ``dz/dt`` and :class:`Aux` (plant input, margin, det K) under :meth:`control`."""
        U, reg = self._control(yref, z, coeffs, g)
        return self.field(z, U, g), Aux(self.plant_control(z, U, g), jnp.abs(reg), reg)

    def error(self, yref, z, g):
        r""":math:`\Psi(z) - \zeta_{ref}`, shape (r, m), angle outputs wrapped (``yref``: (>= r, m))."""
        return self.wrap_error(self.jet(z, g)[0] - yref[: self.relative_degree])

    def solve_top(self, z, target, g):
        """U with ``Y^{(r)} = a(z) + K(z) U = target`` (clamped at :data:`DET_FLOOR`)."""
        _, a, K = self.jet(z, g)
        num, det = _math.adjugate_solve(K, target - a)
        return num / _math.safe_divisor(det, DET_FLOOR)


# --- helpers shared by the sibling controllers -------------------------------------------


def physical_state_names(robot: RobotType) -> tuple:
    """Names of the kinematic state X = (x, y, theta, beta...)."""
    beta = ("beta",) if robot.delta_s == 1 else ("beta1", "beta2")[: robot.delta_s]
    return ("x", "y", "theta") + beta


def validated_physical(robot: RobotType, X, u):
    """(X, u) as float arrays, with a ValueError for wrong shapes or non-finite values (concrete only)."""
    check_real("X", X)
    check_real("u", u)
    X = jnp.asarray(X, dtype=jnp.result_type(float))
    u = jnp.asarray(u, dtype=jnp.result_type(float))
    check_shape("X", X, (robot.n_state,), "(x, y, theta, beta...)")
    check_shape("u", u, (robot.n_input,), "(eta..., zeta...) wheel velocities")
    check_finite("X", X)
    check_finite("u", u)
    return X, u


def make_gains(gains, poles, m: int, r: int):
    """The law's gains: ``gains`` if given (a :class:`wmrjax.Gains` checked (m, r) and Hurwitz, or a
    :class:`wmrjax.GainSchedule` checked (m, r)), else real ``poles``."""
    if gains is not None:
        if not isinstance(gains, (Gains, GainSchedule)):
            raise ValueError(
                f"gains must be a wmrjax.Gains (Hurwitz coefficients) or a wmrjax.GainSchedule, "
                f"got {type(gains).__name__}"
            )
        return gains.check(m, r)
    # (text is refused by Gains.from_poles with the others; jnp.asarray would raise a raw TypeError)
    if not isinstance(poles, (str, bytes)) and jnp.iscomplexobj(jnp.asarray(poles)):
        raise ValueError(
            "poles must be real pole magnitudes (poles at -poles); for complex pole pairs pass "
            "gains=wmrjax.Gains.from_damping(omega, zeta, m=...)"
        )
    return Gains.from_poles(poles, m, r)


def check_reference_type(reference) -> None:
    """ValueError unless ``reference`` is a :class:`Reference` whose path returns a (2,) position."""
    if not isinstance(reference, Reference):
        raise ValueError(f"reference must be a wmrjax.references.Reference, got {type(reference).__name__}")
    if reference.path is None:
        raise ValueError("reference.path is None: build references with wmrjax.references (e.g. from_function)")
    try:
        out = jax.eval_shape(reference.path, jax.ShapeDtypeStruct((), jnp.result_type(float)), reference.params)
    except Exception as exc:  # a path that cannot be traced (NumPy calls, Python control flow on t)
        raise ValueError(
            f"reference {reference.name!r}: its path(t, params) cannot be traced by JAX ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:200]}); write it with jax.numpy so that its derivatives exist"
        ) from None
    if getattr(out, "dtype", None) is not None and jnp.issubdtype(out.dtype, jnp.complexfloating):
        raise ValueError(
            f"reference {reference.name!r}: path(t, params) returns complex numbers ({out.dtype}); a "
            "position (x, y) must be real [m]"
        )
    if getattr(out, "shape", None) != (2,):
        raise ValueError(
            f"reference {reference.name!r}: path(t, params) must return the position (x, y) of shape (2,) "
            f"[m], got {getattr(out, 'shape', type(out).__name__)}; a heading comes from the path's "
            "tangent (add a constant with heading_offset)"
        )


def _concrete_horizon(t0, t_final):
    """``(t0, t_final)`` as floats, checked (finite, ordered); None with a warning where either is
    traced (the reference checks are eager: a user's own call inside jax.jit or jax.vmap)."""
    for name, v in (("t0", t0), ("t_final", t_final)):
        c = concrete(v)
        if c is None:  # simulate calls it with concrete times only: this is a user's own call
            warnings.warn(
                f"check_reference: {name} is traced (inside jax.jit or jax.vmap), so the reference is "
                "not checked; call check_reference outside the trace with concrete times",
                stacklevel=3,  # the caller of check_reference
            )
            return None
        if not (np.ndim(c) == 0 and np.isfinite(c)):
            raise ValueError(f"{name} must be a finite time [s], got {v!r}")
    t0, t_final = float(t0), float(t_final)
    if not t_final > t0:
        raise ValueError(f"the horizon must end after it starts: t0 = {t0} s, t_final = {t_final} s")
    return t0, t_final


def _message_of(check, *args, **kwargs) -> str | None:
    """The message of the ValueError ``check(*args, **kwargs)`` raises, or None."""
    try:
        check(*args, **kwargs)
    except ValueError as err:
        return str(err)
    return None


# --- run checks shared by the siblings ---------------------------------------------------------

_BLOCK = 512  # grid points per compiled evaluation (one compilation per controller)
# the check's program runs a few times per problem: compiled at XLA's lowest backend
# optimization level, which halves its compile (its values differ at most by rounding, far
# below the check's floor and kink tolerance)
CHECK_COMPILE = {"xla_backend_optimization_level": 0}
# Long horizons: that program computes a grid point several times slower than an optimized one
# and pays a call per 512 points, so a grid of more than LONG_CHECK_POINTS points (a horizon of
# about 1300 s) is evaluated by a second program, compiled at the default level, in blocks of
# LONG_BLOCK points: its one extra compile is then smaller than what it saves (the benchmarks
# page has the per-point costs).
LONG_CHECK_POINTS = 2**18
LONG_BLOCK = 2**16
KINK_TOLERANCE = 1e-3  # relative jump of a derivative (per unit step) flagged as a kink

# RK4's stability function R(s) = 1 + s + s^2/2 + s^3/6 + s^4/24; |R| <= 1 on its region
_RK4 = np.array([1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0])


def rk4_amplification(s):
    """``|R(s)|`` of classical RK4 at ``s = dt * lambda`` (stable where <= 1)."""
    return np.abs(np.polyval(_RK4, np.asarray(s, complex)))


def rk4_max_step(poles) -> float:
    """Largest dt with every ``dt * pole`` in RK4's stability region (poles with Re < 0) [s]."""
    hi = 3.0 / max(float(np.max(np.abs(poles))), 1e-300)
    lo = 0.0
    for _ in range(60):  # the region is star-shaped along these rays: bisect
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.all(rk4_amplification(mid * np.asarray(poles)) <= 1.0) else (lo, mid)
    return lo


def _profile_on(ctrl, ts, params):
    """The reference jet (n, r + 1, m) and the controller's regularity of the reference on ``ts``."""
    jets = jax.vmap(lambda t: ctrl.reference_jet(t, params))(ts)
    level, branch = jax.vmap(lambda t: ctrl.reference_regularity(t, params))(ts)
    return jets, level, branch


def _profiles_on(ctrl, ts, stacked):
    """:func:`_profile_on` of every parameter set of ``stacked`` (leaves with a leading axis)."""
    return jax.vmap(lambda p: _profile_on(ctrl, ts, p))(stacked)


_reference_profile = functools.partial(jax.jit, static_argnums=0, compiler_options=CHECK_COMPILE)(_profile_on)
_reference_profile_long = functools.partial(jax.jit, static_argnums=0)(_profile_on)
_reference_profiles = functools.partial(jax.jit, static_argnums=0, compiler_options=CHECK_COMPILE)(_profiles_on)


def _check_grid(t0: float, t_final: float, step: float) -> np.ndarray:
    """The uniform grid of spacing <= ``step`` over [t0, t_final] (at least its two ends)."""
    n = max(2, int(np.ceil((t_final - t0) / step - 1e-9)) + 1)
    return np.linspace(t0, t_final, n)


def _evaluate_blocks(program, ctrl, params, ts, block: int, batched: bool = False):
    """``(jets, level, branch)`` of ``program(ctrl, times, params)`` over ``ts`` in padded blocks of
    ``block`` times (after a leading axis of parameter sets where ``batched``); None if traced."""
    blocks = []
    for i in range(0, ts.size, block):
        tb = ts[i : i + block]
        pad = np.concatenate([tb, np.full(block - tb.size, tb[-1])])
        if jax_core.trace_state_clean():  # the compiled program, called as it is
            out = program(ctrl, jnp.asarray(pad, dtype=jnp.result_type(float)), params)
        else:  # concrete params inside an outer jit: still checked (slower: the call is traced each time)
            with jax.ensure_compile_time_eval():
                out = program(ctrl, jnp.asarray(pad, dtype=jnp.result_type(float)), params)
        out = [concrete(x) for x in out]
        if any(x is None for x in out):
            return None
        blocks.append(out)
    axis = int(batched)
    cut = (slice(None),) * axis + (slice(0, ts.size),)
    return tuple(np.concatenate([b[k] for b in blocks], axis=axis)[cut] for k in range(3))


def reference_profile(ctrl, params, t0: float, t_final: float, step: float = REFERENCE_GRID_STEP):
    """``(ts, jets, level, branch)`` as NumPy arrays on a uniform grid of spacing <= ``step``
    over [t0, t_final], evaluated in fixed-size compiled blocks; None if ``params`` are traced."""
    if any(not is_concrete(x) for x in jax.tree_util.tree_leaves(params)):
        return None  # traced (inside vmap/shard_map): checked by the caller
    ts = _check_grid(t0, t_final, step)
    long = ts.size > LONG_CHECK_POINTS
    block, program = (LONG_BLOCK, _reference_profile_long) if long else (_BLOCK, _reference_profile)
    out = _evaluate_blocks(program, ctrl, params, ts, block)
    return None if out is None else (ts,) + out


def _stacked(params_list):
    """The parameter sets as one pytree with a leading axis, or None where they do not stack
    (another structure, static field or leaf shape)."""
    flat = [jax.tree_util.tree_flatten(p) for p in params_list]
    treedef = flat[0][1]
    if any(d != treedef for _, d in flat) or any(not is_concrete(x) for leaves, _ in flat for x in leaves):
        return None
    columns = list(zip(*(leaves for leaves, _ in flat)))
    if any(len({(np.shape(x), np.asarray(x).dtype) for x in col}) > 1 for col in columns):
        return None
    return jax.tree_util.tree_unflatten(treedef, [np.stack([np.asarray(x) for x in col]) for col in columns])


def reference_profiles(ctrl, params_list, t0: float, t_final: float, step: float = REFERENCE_GRID_STEP):
    """:func:`reference_profile` of each parameter set of one controller, yielded in order: one
    batched program for all of them (a sweep group's references) where they stack and the grid
    is short, one after the other otherwise. At most ``LONG_CHECK_POINTS`` grid points of
    profiles are held at a time (sets beyond that go in further batches of the same size)."""
    params_list = list(params_list)
    ts = _check_grid(t0, t_final, step)
    padded = -(-ts.size // _BLOCK) * _BLOCK  # the grid as evaluated: whole blocks
    size = min(len(params_list), max(1, LONG_CHECK_POINTS // padded))
    if size < 2:
        yield from (reference_profile(ctrl, p, t0, t_final, step) for p in params_list)
        return
    for i in range(0, len(params_list), size):
        chunk = params_list[i : i + size]
        stacked = _stacked(chunk + [chunk[-1]] * (size - len(chunk)))  # one batch size: one compiled program
        if stacked is None:  # another structure, static field or leaf shape among them
            yield from (reference_profile(ctrl, p, t0, t_final, step) for p in chunk)
            continue
        out = _evaluate_blocks(_reference_profiles, ctrl, stacked, ts, _BLOCK, batched=True)
        yield from ((None if out is None else (ts,) + tuple(x[j] for x in out)) for j in range(len(chunk)))


def find_kink(ts, jets, angle_outputs=()):
    r"""First grid interval where a derivative the law uses jumps, or None.

    On each interval of length h the trapezoid rule predicts :math:`Y^{(j)}(t_{k+1}) -
    Y^{(j)}(t_k)` from :math:`Y^{(j+1)}` to :math:`h^3 |Y^{(j+3)}|/12` for a smooth path; a
    jump J of :math:`Y^{(j+1)}` at fraction :math:`\theta` of the interval leaves a residual
    :math:`J h |1/2 - \theta|` (so callers also run it on the midpoints' grid).
    Flagged: a residual above ``KINK_TOLERANCE * h * (1 + max|Y^{(j+1)}|)``.

    Returns:
      ``(t_k, t_{k+1}, j, residual)`` or None.
    """
    h = np.diff(ts)[:, None]
    for j in range(jets.shape[1] - 1):
        d = np.diff(jets[:, j], axis=0)
        if j == 0 and angle_outputs:
            idx = list(angle_outputs)
            d[:, idx] = (d[:, idx] + np.pi) % (2 * np.pi) - np.pi
        res = np.abs(d - 0.5 * h * (jets[1:, j + 1] + jets[:-1, j + 1]))
        scale = 1.0 + np.max(np.abs(jets[:, j + 1]), axis=0)
        bad = res > KINK_TOLERANCE * h * scale
        if bad.any():
            k = int(np.argmax(bad.any(axis=1)))
            return float(ts[k]), float(ts[k + 1]), j + 1, float(res[k].max())
    return None


# a time beyond this [s] is a clock reading (epoch seconds), not a time from the start
CLOCK_TIME_S = 1e6
# a speed below this fraction of the largest is a stop
STOP_FRACTION = 1e-3


def kink_cause(ts, jets) -> str:
    """The likeliest cause of a failed kink test, for its message: float32 round-off, times
    that are clock readings, a path that stops, or else a kink or corner."""
    if jnp.result_type(float) == jnp.float32:
        return (
            "float32 round-off: JAX runs in single precision, and the test's finite differences need "
            "double; enable it with jax.config.update('jax_enable_x64', True) before building anything"
        )
    if np.max(np.abs(ts)) > CLOCK_TIME_S:
        return (
            f"times up to {np.max(np.abs(ts)):.4g} s look like clock readings (epoch seconds), where the "
            "path's polynomials lose their digits: subtract the first sample time so the path starts at 0"
        )
    speed = np.linalg.norm(jets[:, 1, :2], axis=-1)
    if speed.size and np.min(speed) < STOP_FRACTION * max(np.max(speed), 1e-300):
        return (
            f"the path stops: its speed falls to {np.min(speed):.3g} m/s at t = {ts[int(np.argmin(speed))]:.4g} s "
            "(a stop or a turn on the spot); plan a path that keeps moving"
        )
    return "a kink or corner in the path"


@functools.partial(jax.jit, static_argnums=0)
def margin_at(ctrl, z, params):
    """``ctrl.margin(z, params)``, compiled once per controller (the eager jet takes seconds)."""
    return ctrl.margin(z, params)


def check_regular(ctrl, z, params, name: str, law_name: str, table: str, regularity: str) -> None:
    """ValueError if a concrete state ``z`` is on (or numerically at) the singular set."""
    zc = concrete(z)
    if zc is None:
        return
    check_shape(name, zc, (ctrl.n_state,), " ".join(ctrl.state_names))
    check_finite(name, zc)
    m = concrete(margin_at(ctrl, jnp.asarray(zc), params))
    if m is None:  # traced parameters (e.g. vmap over geometry): checked by the caller's caller
        return
    m = float(m)
    if not m > 1e3 * DET_FLOOR:
        raise ValueError(
            f"{name} is on the singular set of the {law_name} for type {ctrl.robot.name}: "
            f"margin |det K| = {m:.3g}; {table} requires {regularity}"
        )


class LinearizingController(ClosedLoop):
    """What both sibling controllers delegate to their :class:`LinearizingLaw` (a method mixin).

    :class:`~wmrjax.controllers.DynamicLinearization` and
    :class:`~wmrjax.controllers.StaticLinearization` are frozen dataclasses with a table
    ``row`` (whose ``extension`` the law runs) and a ``level``; each adds its own reference
    jet (``reference_jet(t, params)``: Table 4's outputs of the reference posture, or Table
    3's point path), parameters, initial states and checks. Neither is a kind of the other.
    Methods take ``(t, z, params)`` or ``(z, params)``.
    """

    _law_name = ""  # for messages: "dynamic linearizing law", "static linearizing law"
    _table = ""  # "Table 4", "Table 3"

    @property
    def law(self) -> LinearizingLaw:
        """The generic law this controller runs (one implementation for both siblings)."""
        return LinearizingLaw(self.row.extension, self.level)

    @property
    def robot(self) -> RobotType:
        """The robot type."""
        return self.row.robot

    @property
    def m(self) -> int:
        """The number of linearized outputs."""
        return self.law.m

    @property
    def relative_degree(self) -> int:
        """The relative degree of each output."""
        return self.law.relative_degree

    @property
    def n_state(self) -> int:
        """The closed loop's state size."""
        return self.law.n_state

    def reference_jet_floats(self) -> int:
        """The reference check's numbers per time: every output's jet up to the relative degree."""
        return (self.relative_degree + 1) * self.m

    @property
    def path_order(self) -> int:
        """The highest derivative of the reference path p(t) that :meth:`reference_jet` uses: the
        outputs' derivative of order r, of a posture whose heading is the tangent of p (one
        order more). A sampled path must keep it continuous (:func:`wmrjax.references.spline_degree_for`)."""
        return self.relative_degree + 1

    def outputs(self, z, params):
        """Linearizing outputs Y at ``z``, shape (m,)."""
        return self.law.outputs(z, params.geometry)

    def jet(self, z, params):
        """``(zeta, a, K)`` of :func:`wmrjax.linearize.output_jet` at ``z``."""
        return self.law.jet(z, params.geometry)

    def psi(self, z, params):
        r"""The output jet :math:`\zeta = \Psi(z)` (eq 35), shape (r, m)."""
        return self.law.jet(z, params.geometry)[0]

    def control(self, t, z, params):
        """New input U of eq (49) (the plant input for a static law) and the margin; the division
        by ``det K`` is clamped at :data:`DET_FLOOR`."""
        return self.law.control(self.reference_jet(t, params), z, params.gains.coeffs_at(t), params.geometry)

    def control_and_regularity(self, t, z, params):
        """``(U, det K)``: the law's new input and its signed regularity (zero on the singular set;
        a sign change between two evaluations of a run is a crossing)."""
        return self.law._control(self.reference_jet(t, params), z, params.gains.coeffs_at(t), params.geometry)

    def control_and_error(self, t, z_measured, z_true, params, jet=None):
        """``(U, det K, error)`` at one time from one evaluation of the reference's jet: the law at
        the measured state (:meth:`control_and_regularity`) and the output error of the true one
        (:meth:`error`), as a digital controller's sample needs them. ``jet``: the reference's jet
        at ``t`` where the caller has it (an enclosure of the sampled loop evaluates it in floats,
        at a point, where interval rules would straddle a sampled path's knot)."""
        jet = self.reference_jet(t, params) if jet is None else jet
        U, reg = self.law._control(jet, z_measured, params.gains.coeffs_at(t), params.geometry)
        return U, reg, self.law.error(jet, z_true, params.geometry)

    def margin(self, z, params):
        """Singularity margin at ``z``: ``|det K|`` (times the row's extra factor, the (1,1) lever of
        Table 4); 0 on the singular set."""
        return self.law.margin(z, params.geometry)

    def vector_field(self, t, z, params):
        """Closed-loop ``dz/dt`` and :class:`Aux` (plant input, margin)."""
        return self.law.closed_loop(self.reference_jet(t, params), z, params.gains.coeffs_at(t), params.geometry)

    def error(self, t, z, params):
        r""":math:`\tilde\zeta = \Psi(z) - \zeta_{ref}(t)`, shape (r, m); angle outputs wrapped."""
        return self.law.error(self.reference_jet(t, params), z, params.geometry)

    def error_matrix(self, gains: Gains):
        r"""Matrix A with :math:`\dot{\tilde\zeta} = A \tilde\zeta` on ``error(...).reshape(-1)``
        (a :class:`wmrjax.GainSchedule` gives its A(0); its transition matrix is
        :func:`wmrjax.linearize.transition_matrix`)."""
        return linearize.companion(gains.coeffs_at(0.0))

    def check_regular(self, z, params, name: str = "initial state") -> None:
        """Raise ValueError if a concrete ``z`` is on (or numerically at) the row's singular set."""
        check_regular(self, z, params, name, self._law_name, self._table, self.row.regularity)

    # -- run checks --
    def check_params(self, params) -> None:
        """ValueError unless ``params`` are this controller's (type, gain shape, reference type)."""
        want = self._params_type
        if not isinstance(params, want):
            raise ValueError(
                f"params must be the {want.__name__} of this {self._law_name} (type {self.robot.name}, "
                f"{self.level} level; build them with its .params()), got {type(params).__name__}"
            )
        shape = tuple(params.gains.shape)
        if shape[-2:] != (self.m, self.relative_degree):
            raise ValueError(
                f"params.gains.coeffs must have shape ({self.m}, {self.relative_degree}) for this "
                f"{self._law_name} (type {self.robot.name}, {self.level} level: m = {self.m} outputs, "
                f"relative degree {self.relative_degree}), got {shape}: parameters of another controller?"
            )
        check_reference_type(params.reference)

    def error_poles(self, gains: Gains):
        """Eigenvalues of the error dynamics (the closed-loop poles), or None for traced gains."""
        c = concrete(gains.coefficient_samples())
        if c is None or np.ndim(c) != 3:
            return None
        c = np.asarray(c).reshape(-1, np.shape(c)[-1])  # every output (at every knot of a schedule)
        # the roots of each output's polynomial s^r + k_{r-1} s^{r-1} + ... + k_0 (NumPy: also
        # concrete inside a jit trace, where jnp would stage the computation)
        return np.concatenate([np.roots(np.concatenate([[1.0], row[::-1]])) for row in np.asarray(c, float)])

    def check_step(self, params, dt) -> None:
        """ValueError if ``dt`` times a closed-loop pole lies outside RK4's stability region."""
        dtv, poles = concrete(dt), self.error_poles(params.gains)
        if dtv is None or poles is None or np.ndim(poles) != 1:
            return
        amp = rk4_amplification(float(dtv) * poles)
        if np.any(amp > 1.0):
            i = int(np.argmax(amp))
            raise ValueError(
                f"dt = {float(dtv):.4g} s is outside RK4's stability region for this closed loop: "
                f"its error dynamics have a pole at {complex(poles[i]):.4g} 1/s, and |R(dt * pole)| = "
                f"{amp[i]:.3g} > 1, so the run would diverge numerically; use dt <= "
                f"{rk4_max_step(poles):.4g} s (and much smaller for accuracy)"
            )

    def check_reference(self, params, t_final, *, t0=0.0, floor: float = 1e-6) -> None:
        """ValueError if the reference is unusable on [t0, t_final]: it reaches the singular set
        (a stop, a reversal, the wrong branch) or has a kink (a jump in a derivative the law
        uses), checked on a grid of spacing <= :data:`REFERENCE_GRID_STEP`. No-op for traced params;
        with a traced ``t0`` or ``t_final`` it warns that nothing was checked (checks are eager)."""
        horizon = _concrete_horizon(t0, t_final)
        if horizon is None:
            return
        self._check_reference_domain(params, *horizon)
        # a grid of half the spacing: the kink test runs on its even and its odd points, so a jump
        # in the middle of an interval of one lies on a point of the other (residual >= J h / 4)
        prof = reference_profile(self, params, *horizon, REFERENCE_GRID_STEP / 2)
        if prof is not None:
            self._judge_reference(params, prof, *horizon, floor)

    def reference_errors(self, params_list, t_final, *, t0=0.0, floor: float = 1e-6) -> list:
        """:meth:`check_reference` of several parameter sets (a sweep group's references): their
        profiles evaluated by one batched program where they stack. Returns, for each set, the
        message of the ValueError :meth:`check_reference` would raise for it, or None. A bad
        horizon raises its ValueError, as :meth:`check_reference` does."""
        horizon = _concrete_horizon(t0, t_final)
        params_list = list(params_list)
        if horizon is None:
            return [None] * len(params_list)
        errors = [_message_of(self._check_reference_domain, p, *horizon) for p in params_list]
        pending = [j for j, e in enumerate(errors) if e is None]
        step = REFERENCE_GRID_STEP / 2
        done = 0
        try:
            for j, prof in zip(pending, reference_profiles(self, [params_list[j] for j in pending], *horizon, step)):
                errors[j] = (
                    None if prof is None else _message_of(self._judge_reference, params_list[j], prof, *horizon, floor)
                )
                done += 1
        except ValueError:  # the batched evaluation itself refused: each set on its own, as check_reference does
            for j in pending[done:]:
                errors[j] = _message_of(self.check_reference, params_list[j], horizon[1], t0=horizon[0], floor=floor)
        return errors

    def _check_reference_domain(self, params, t0: float, t_final: float) -> None:
        """ValueError if [t0, t_final] leaves the reference's samples or its check would not fit in memory."""
        check_domain(params.reference, t0, t_final)
        resources.check_fits(
            resources.Estimate(0.0, resources.check_bytes(t_final - t0, self.reference_jet_floats())),
            f"the reference check over [{t0:g}, {t_final:g}] s (its derivatives every {REFERENCE_GRID_STEP / 2:g} s)",
            "shorten the horizon",
        )

    def _judge_reference(self, params, prof, t0: float, t_final: float, floor: float) -> None:
        """ValueError if the profile ``(ts, jets, level, branch)`` of :func:`reference_profile`
        reaches the singular set, has a non-finite derivative or a kink."""
        ts, jets, level, branch = prof
        level = self._reference_level(level, params)
        low = ~np.isfinite(level) | (level <= floor)
        other = np.sign(branch) != self.reference_branch(params)
        if low.any():
            i = int(np.argmax(low))
            raise ValueError(
                f"reference {params.reference.name!r} reaches the singular set of the {self._law_name} (type "
                f"{self.robot.name}) at t = {ts[i]:.4g} s: its regularity {level[i]:.3g} is at or below the floor "
                f"{floor:g}; {self._table} requires {self._reference_requirement} on [{t0:g}, {t_final:g}] s "
                "(it must not stop or reverse)"
            )
        if other.any():
            i = int(np.argmax(other))
            raise ValueError(self._branch_message(params, ts[i], level[i], t0, t_final))
        if not np.all(np.isfinite(jets)):
            i = int(np.argmax(~np.isfinite(jets).reshape(len(ts), -1).all(axis=1)))
            raise ValueError(f"reference {params.reference.name!r} has a non-finite derivative at t = {ts[i]:.4g} s")
        found = [
            k
            for k in (
                find_kink(ts[i::2], jets[i::2], self.row.extension.angle_outputs)
                for i in ((0, 1) if len(ts) > 3 else (0,))
            )
            if k is not None
        ]
        kink = min(found, key=lambda k: (k[2], k[0])) if found else None  # the lowest order, the earliest
        if kink is not None:
            a, b, j, res = kink
            raise ValueError(
                f"reference {params.reference.name!r} is not smooth enough for the {self._law_name}: its "
                f"derivative of order {j} jumps between t = {a:.4g} and {b:.4g} s (trapezoid residual "
                f"{res:.3g}); the law uses derivatives up to order {self.relative_degree}, which must be "
                f"continuous ({self._kink_cause(params, ts, jets)})"
            )

    def _kink_cause(self, params, ts, jets) -> str:
        """:func:`kink_cause`, or a sampled path whose spline is of too low a degree for this law."""
        pp = params.reference.params.get("pp") if isinstance(params.reference.params, dict) else None
        if pp is not None and np.shape(pp)[-2] - 2 < self.path_order:
            return (
                f"the path is a spline of degree {np.shape(pp)[-2] - 1}, whose derivative of order "
                f"{np.shape(pp)[-2] - 1} jumps at every sample, and this law uses the path's derivative of "
                f"order {self.path_order}: build it with degree={spline_degree_for(self.path_order)} "
                "(problem files do)"
            )
        return kink_cause(ts, jets)

    def _branch_message(self, params, t: float, level: float, t0: float, t_final: float) -> str:
        """Why a regular reference is refused for its branch (Remark 17): the message names the key."""
        return (
            f"reference {params.reference.name!r} is regular at t = {t:.4g} s (regularity {level:.3g}) but moves "
            f"on the other branch than its heading offset gives on [{t0:g}, {t_final:g}] s; the direction of "
            "travel is set by the heading offset ([reference] heading_offset: 0 drives along the body's +x2, "
            "pi along -x2)"
        )

    def _reference_level(self, raw, params):
        """The regularity level (>= 0, 0 singular) from what ``reference_regularity`` returned."""
        del params
        return raw

    def check_run(self, params, *, t0, dt, n_steps: int) -> None:
        """What :func:`wmrjax.simulate` checks before compiling: these are this controller's
        parameters, ``dt`` is stable for the error dynamics, the reference is usable over the run."""
        self.check_params(params)
        self.check_step(params, dt)
        dtv, t0v = concrete(dt), concrete(t0)
        if dtv is not None and t0v is not None:
            self.check_reference(params, float(t0v) + n_steps * float(dtv), t0=float(t0v))

    def _unchecked_gains(self, poles) -> Gains:
        """Real poles broadcast to (m, r), without validation (traced values)."""
        p = jnp.broadcast_to(jnp.asarray(poles, dtype=jnp.result_type(float)), (self.m, self.relative_degree))
        return Gains.from_poles(p)
