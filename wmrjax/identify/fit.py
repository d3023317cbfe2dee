r"""Maximum-likelihood identification of a plant from its logs, with intervals.

**Model.** Each log is cut into *segments* of ``FitOptions.segment`` seconds; each segment's
initial state (the posture, and at torque level the velocities) is a free nuisance parameter
and its samples are predicted open loop by :func:`wmrjax.identify.model.predict` from the
logged commands (multiple shooting without continuity constraints: a log's drift -- slip, or an
unmodelled disturbance -- cannot accumulate beyond one segment, and the initial state is never
taken from a noisy measurement as if exact). The measurements are the prediction plus
independent Gaussian noise of one standard deviation per channel (x, y, theta, beta...);
angles' residuals are wrapped to :math:`(-\pi, \pi]`.

**Fit.** Levenberg-Marquardt on the whitened residuals, the Jacobian by forward-mode JAX
through the simulation, the normal equations solved by eliminating each segment's initial
state (a Schur complement: the segments couple only through the plant's parameters); each
channel's noise variance is re-estimated between solves (the residual sum of squares over the
degrees of freedom left) until it settles, which is the joint maximum of the likelihood.

**Intervals.** Standard errors from the inverse of the Gauss-Newton Hessian of the negative
log-likelihood (:math:`J^T W J`, the expected Fisher information) at the estimate, the
segments' initial states eliminated; 95 % intervals are estimate +- 1.96 standard errors. A
parameter is *not identifiable* when the logs do not see it (its Jacobian column is zero, e.g.
``geometry_scale`` of a (2,0) robot, whose kinematics contain neither L nor e), when the
segments' initial states absorb it, or when it trades off exactly with others (a null direction
of the information): it is then held at its nominal value, named, and given no number.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math
from wmrjax.controllers.law import Level
from wmrjax.identify.logs import Log, check_log
from wmrjax.identify.model import InputParams, LoggedInputs, predict
from wmrjax.robots import Geometry, RobotType, input_matrix

Z95 = 1.959963984540054  # the standard normal's 0.975 quantile
# a global parameter whose Jacobian column is below this fraction of the largest is not seen
UNSEEN_RTOL = 1e-8
# a parameter whose information left after the initial states is below this fraction of its own
ABSORBED_RTOL = 1e-8
# a direction of the (correlation-scaled) information below this fraction of its largest
NULL_RTOL = 1e-10


@dataclasses.dataclass(frozen=True)
class PlantModel:
    """What is known of the plant before the fit (static).

    Attributes:
      robot: the robot type.
      level: the level of the logged commands.
      geometry: the law's nominal geometry (the plant's is ``geometry_scale`` times its L and e).
      input_limit: (n_input,) the plant's limits (inf: none), as the problem's ``[plant]`` states.
      period: the controller period [s]: one log row per period.
      substeps: RK4 steps per period.
    """

    robot: RobotType
    level: Level
    geometry: Geometry
    input_limit: tuple
    period: float
    substeps: int = 4

    @property
    def names(self) -> tuple:
        """The plant's parameters, named as the problem file's ``[plant]`` names them."""
        return ("geometry_scale",) + tuple(f"input_scale_{i + 1}" for i in range(self.robot.n_input))

    @property
    def channels(self) -> tuple:
        """The measured channels: ``x, y, theta, beta1, ...``."""
        return ("x", "y", "theta") + tuple(f"beta{i + 1}" for i in range(self.robot.delta_s))

    @property
    def system(self) -> LoggedInputs:
        """The logged-inputs system the fit integrates."""
        return LoggedInputs(self.robot, self.level, self.substeps)

    @property
    def n_initial(self) -> int:
        """Size of a segment's initial state (X, and u at torque level)."""
        return self.system.n_plant


class FitOptions(NamedTuple):
    """How the fit runs.

    Attributes:
      segment: a segment's duration [s] (its initial state is fitted; shorter: more robust to
        drift, less information per parameter).
      max_delay: the largest input delay tried, in whole samples (0: none); the delay with the
        largest likelihood is selected (on the same samples for every candidate).
      max_iterations: Levenberg-Marquardt iterations per noise level.
      rtol: the fit has converged when an accepted step lowers the cost by less than this fraction.
    """

    segment: float = 2.0
    max_delay: int = 0
    max_iterations: int = 60
    rtol: float = 1e-10


class Estimate(NamedTuple):
    """One identified parameter.

    Attributes:
      name: as the problem file names it (``geometry_scale``, ``input_scale_1``, ``noise_std_x``...).
      estimate: the maximum-likelihood value (None when not identifiable).
      std_error: its standard error (None when not identifiable).
      interval_95: its 95 % interval ``(low, high)`` (None when not identifiable).
      identifiable: whether the logs determine it.
      note: why it is not identifiable ("" when it is).
    """

    name: str
    estimate: float | None
    std_error: float | None
    interval_95: tuple | None
    identifiable: bool
    note: str = ""

    def summary(self) -> dict:
        """The fit as plain JSON."""
        return {
            "estimate": self.estimate,
            "std_error": self.std_error,
            "interval_95": None if self.interval_95 is None else list(self.interval_95),
            "identifiable": self.identifiable,
            **({"note": self.note} if self.note else {}),
        }


class Segments(NamedTuple):
    """Every log cut into segments of one length S (padded; host arrays).

    Attributes:
      measured: (G, S, n_X) measured postures.
      mask: (G, S) 1 on a sample, 0 on padding.
      commands: (G, S, n_input) the command held after each sample (delay applied).
      initial: (G, n_initial) the initial states' first guess.
      log: (G,) which log each segment is from.
      first: (G,) the segment's first row in its log.
    """

    measured: np.ndarray
    mask: np.ndarray
    commands: np.ndarray
    initial: np.ndarray
    log: np.ndarray
    first: np.ndarray


def _initial_velocity(model: PlantModel, t, X) -> np.ndarray:
    """A first guess of the velocities u at a segment's start: a line through its first samples'
    postures, mapped back through the kinematics' pseudo-inverse (eq 5)."""
    m = min(len(t), 8)
    tt = t[:m] - t[0]
    A = np.stack([np.ones(m), tt], axis=1)
    Xs = X[:m].copy()
    Xs[:, 2] = np.unwrap(Xs[:, 2])
    slope = np.linalg.lstsq(A, Xs, rcond=None)[0][1]
    B = np.asarray(_input_matrix(model.robot, jnp.asarray(X[0]), model.geometry))
    return np.linalg.lstsq(B, slope, rcond=None)[0]


_input_matrix = jax.jit(input_matrix, static_argnums=0)


def cut(model: PlantModel, logs: list, length: int, start: int, delay: int) -> Segments:
    """Cut ``logs`` into the fit's :class:`Segments`.

    Args:
      model: the :class:`PlantModel` (at torque level a segment's initial velocities are guessed
        from its first samples).
      logs: the :class:`wmrjax.identify.Log` s.
      length: samples per segment (a last, shorter segment is padded and masked; one of a single
        sample is dropped).
      start: the first row used in every log (the largest delay tried: every delay is then fitted
        on the same samples).
      delay: the commands' delay [rows]: sample i is driven by the command of row i - delay.
    """
    out = {k: [] for k in Segments._fields if k != "commands"}
    for j, log in enumerate(logs):
        n = len(log.t)
        for i0 in range(start, n - 1, length):
            rows = np.minimum(np.arange(i0, i0 + length), n - 1)
            init = log.posture[i0]
            if model.level == Level.TORQUE:
                init = np.concatenate([init, _initial_velocity(model, log.t[i0:], log.posture[i0:])])
            out["measured"].append(log.posture[rows])
            out["mask"].append((np.arange(i0, i0 + length) < n).astype(float))
            out["initial"].append(init)
            out["log"].append(j)
            out["first"].append(i0)
    if not out["log"]:
        raise ValueError(f"the logs have no two samples after the first {start} (the largest delay tried)")
    seg = Segments(
        *(np.asarray(out[k], int if k in ("log", "first") else float) if k in out else None for k in Segments._fields)
    )
    return with_delay(logs, seg, delay)


def with_delay(logs: list, seg: Segments, delay: int) -> Segments:
    """``seg`` with the commands of ``delay`` rows earlier: sample i driven by row i - delay (the
    first row before a log's start). Only the commands change with the delay, so a fit over
    several delays cuts its logs once."""
    length = seg.mask.shape[1]
    commands = []
    for j, i0 in zip(seg.log, seg.first):
        n = len(logs[j].t)
        rows = np.minimum(np.arange(i0, i0 + length), n - 1)
        commands.append(logs[j].command[np.clip(rows - delay, 0, n - 1)])
    return seg._replace(commands=np.asarray(commands, float))


def full_parameters(free: tuple, theta, n: int):
    """The plant's parameter vector ``(geometry_scale, input_scale...)`` with ``theta`` at the
    indices ``free`` and the nominal value 1 elsewhere."""
    return jnp.ones(n, jnp.result_type(theta)).at[jnp.asarray(free, int)].set(theta) if free else jnp.ones(n)


def _segment_residual(model: PlantModel, free: tuple, theta, z0, commands, measured):
    """(S, n_X) measured minus predicted postures of one segment (angles wrapped)."""
    p = full_parameters(free, theta, len(model.names))
    g = model.geometry
    geometry = Geometry(p[0] * g.L, p[0] * g.e, jnp.asarray(g.delta, p.dtype))
    params = InputParams(geometry, p[1:], jnp.asarray(model.input_limit, p.dtype), commands)
    X = predict(model.system, z0, params, model.period)[:, : model.robot.n_state]
    r = measured - X
    return jnp.concatenate([r[:, :2], _math.wrap_angle(r[:, 2:])], axis=1)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _evaluate(model: PlantModel, free: tuple, theta, z0, commands, measured):
    """Residuals (G, S, n_X) and their Jacobians in the free parameters (G, S, n_X, p) and in
    each segment's initial state (G, S, n_X, n_initial)."""

    def one(z, c, m):
        f = lambda th, zz: (_segment_residual(model, free, th, zz, c, m),) * 2
        (jt, jz), r = jax.jacfwd(f, argnums=(0, 1), has_aux=True)(theta, z)
        return r, jt, jz

    return jax.vmap(one)(z0, commands, measured)


class _Normal(NamedTuple):
    """The whitened normal equations, the initial states' blocks kept apart (host arrays)."""

    A: np.ndarray  # (p, p) plant parameters
    B: np.ndarray  # (G, p, n0) plant x initial state
    C: np.ndarray  # (G, n0, n0) initial states
    a: np.ndarray  # (p,) gradient in the plant parameters
    c: np.ndarray  # (G, n0) gradient in the initial states
    cost: float  # half the whitened residual sum of squares


def _normal(r, jt, jz, mask, sigma) -> _Normal:
    w = mask[..., None] / sigma  # (G, S, n_X)
    rw, jtw, jzw = r * w, jt * w[..., None], jz * w[..., None]
    return _Normal(
        np.einsum("gsip,gsiq->pq", jtw, jtw),
        np.einsum("gsip,gsiq->gpq", jtw, jzw),
        np.einsum("gsip,gsiq->gpq", jzw, jzw),
        np.einsum("gsip,gsi->p", jtw, rw),
        np.einsum("gsip,gsi->gp", jzw, rw),
        0.5 * float(np.sum(rw**2)),
    )


def _damped(M, lam):
    d = np.diagonal(M, axis1=-2, axis2=-1)
    floor = 1e-12 * max(float(np.max(d)) if d.size else 1.0, 1e-300)
    return M + lam * np.apply_along_axis(np.diag, -1, np.maximum(d, floor))


def _step(ne: _Normal, lam: float, fit_plant: bool):
    r"""The Levenberg-Marquardt step ``(d_theta, d_z0)`` of :math:`(J^TJ + \lambda D)\delta = -J^Tr`,
    the initial states eliminated (each segment's block solved on its own)."""
    C = _damped(ne.C, lam)
    Cinv_c = np.linalg.solve(C, ne.c[..., None])[..., 0]
    if fit_plant and ne.A.size:
        Cinv_Bt = np.linalg.solve(C, np.swapaxes(ne.B, 1, 2))  # (G, n0, p)
        S = _damped(ne.A, lam) - np.einsum("gpk,gkq->pq", ne.B, Cinv_Bt)
        rhs = -ne.a + np.einsum("gpk,gk->p", ne.B, Cinv_c)
        dt = np.linalg.solve(S, rhs)
    else:
        dt = np.zeros(ne.a.shape)
    dz = -Cinv_c - np.linalg.solve(C, np.einsum("gpk,p->gk", ne.B, dt)[..., None])[..., 0]
    return dt, dz


class _State(NamedTuple):
    theta: np.ndarray
    z0: np.ndarray
    r: np.ndarray
    jt: np.ndarray
    jz: np.ndarray


def _eval(model, free, theta, z0, seg: Segments) -> _State:
    r, jt, jz = _evaluate(model, free, jnp.asarray(theta), jnp.asarray(z0), seg.commands, seg.measured)
    return _State(theta, z0, np.asarray(r), np.asarray(jt), np.asarray(jz))


def _levenberg_marquardt(model, free, st: _State, seg, sigma, options: FitOptions, fit_plant=True):
    """``(state, iterations, converged)``: Levenberg-Marquardt at fixed noise levels ``sigma``."""
    lam, ne = 1e-3, _normal(st.r, st.jt, st.jz, seg.mask, sigma)
    for it in range(1, options.max_iterations + 1):
        dt, dz = _step(ne, lam, fit_plant)
        trial = _eval(model, free, st.theta + dt, st.z0 + dz, seg)
        nt = _normal(trial.r, trial.jt, trial.jz, seg.mask, sigma)
        if np.isfinite(nt.cost) and nt.cost <= ne.cost:
            gain = ne.cost - nt.cost
            st, ne, lam = trial, nt, max(lam / 3.0, 1e-12)
            if gain <= options.rtol * max(ne.cost, 1e-300):
                return st, ne, it, True
        else:
            lam *= 4.0
            if lam > 1e12:  # no descent left: at a minimum to rounding
                return st, ne, it, True
    return st, ne, options.max_iterations, False


def _noise(r, mask, n_free: int):
    """Each channel's noise std from the residuals: its sum of squares over its share of the
    degrees of freedom left after the fit's ``n_free`` parameters."""
    n = float(np.sum(mask))
    rss = np.einsum("gs,gsi->i", mask, r**2)
    dof = n * max(1.0 - n_free / (n * r.shape[-1]), 1e-3)
    return np.sqrt(np.maximum(rss / dof, 1e-300)), dof


class _Fit(NamedTuple):
    state: _State
    normal: _Normal
    sigma: np.ndarray
    dof: float
    nll: float  # profile negative log-likelihood (the noise at its maximum-likelihood value)
    iterations: int
    converged: bool


def _fit(model, free, seg: Segments, options: FitOptions, theta=None, fit_plant=True) -> _Fit:
    """Alternate Levenberg-Marquardt and the noise levels until the noise settles."""
    theta = np.ones(len(free)) if theta is None else theta
    st = _eval(model, free, theta, seg.initial, seg)
    n_free = (len(free) if fit_plant else 0) + seg.initial.size
    sigma, dof = _noise(st.r, seg.mask, n_free)
    total, converged = 0, False
    for _ in range(12):
        st, ne, its, converged = _levenberg_marquardt(model, free, st, seg, sigma, options, fit_plant)
        total += its
        new, dof = _noise(st.r, seg.mask, n_free)
        settled = np.max(np.abs(new / sigma - 1.0)) < 1e-6
        sigma = new
        if settled:
            break
    ne = _normal(st.r, st.jt, st.jz, seg.mask, sigma)
    n = float(np.sum(seg.mask))
    rss = np.einsum("gs,gsi->i", seg.mask, st.r**2)
    nll = float(0.5 * n * np.sum(np.log(rss / n)) + 0.5 * n * len(sigma) * (1.0 + math.log(2 * math.pi)))
    return _Fit(st, ne, sigma, dof, nll, total, converged)


def _reduced_information(ne: _Normal) -> np.ndarray:
    """The plant parameters' information with the initial states eliminated (Schur complement)."""
    if not ne.A.size:
        return ne.A
    return ne.A - np.einsum("gpk,gkq->pq", ne.B, np.linalg.solve(ne.C, np.swapaxes(ne.B, 1, 2)))


def not_identifiable(names: tuple, free: tuple, fit: _Fit) -> dict:
    """``{index: why}`` of the free parameters the logs do not determine (module docstring)."""
    ne, out = fit.normal, {}
    if not free:
        return out
    col = np.sqrt(np.einsum("gsip,gsip->p", fit.state.jt, fit.state.jt))
    for k, i in enumerate(free):
        if col[k] <= UNSEEN_RTOL * max(float(np.max(col)), 1e-300) or col[k] == 0.0:
            out[i] = "the logs do not see it: the plant's kinematics do not depend on it"
    F = _reduced_information(ne)
    d = np.diagonal(ne.A)
    for k, i in enumerate(free):
        if i not in out and F[k, k] <= ABSORBED_RTOL * d[k]:
            out[i] = "the segments' initial states absorb it (lengthen the segments, or excite it more)"
    keep = [k for k, i in enumerate(free) if i not in out]
    if len(keep) > 1:
        Fk = F[np.ix_(keep, keep)]
        s = 1.0 / np.sqrt(np.diagonal(Fk))
        lam, vec = np.linalg.eigh(Fk * s[:, None] * s[None, :])
        for j in np.flatnonzero(lam <= NULL_RTOL * lam[-1]):
            involved = [keep[k] for k in np.flatnonzero(np.abs(vec[:, j]) > 0.2)]  # positions in free
            for q in involved:
                others = ", ".join(names[free[m]] for m in involved if m != q)
                out[free[q]] = f"it trades off with {others}: the logs determine only a combination"
    return out


class Identification(NamedTuple):
    """What :func:`identify` found (host values).

    Attributes:
      model: the :class:`PlantModel` fitted.
      parameters: one :class:`Estimate` per plant parameter (:attr:`PlantModel.names`).
      noise_std: one :class:`Estimate` per measured channel (``noise_std_x``, ...) [m or rad].
      delay: the selected input delay [samples].
      delay_nll: the profile negative log-likelihood of each delay tried (index = delay).
      checks: one :class:`wmrjax.identify.LogCheck` per log.
      log_names: the logs' names.
      residual_rms: (n_logs, n_X) root-mean-square residual per log and channel [m or rad].
      segments: the :class:`Segments` fitted (the selected delay's commands).
      predicted: (G, S, n_X) the fitted prediction of each segment's samples.
      correlation: (p, p) correlation of the identifiable parameters' estimates (order of
        ``parameters``, the others' rows NaN).
      iterations: Levenberg-Marquardt iterations of the selected fit.
      converged: whether it converged.
      options: the :class:`FitOptions`.
    """

    model: PlantModel
    parameters: tuple
    noise_std: tuple
    delay: int
    delay_nll: tuple
    checks: tuple
    log_names: tuple
    residual_rms: np.ndarray
    segments: Segments
    predicted: np.ndarray
    correlation: np.ndarray
    iterations: int
    converged: bool
    options: FitOptions

    def estimate(self, name: str) -> Estimate:
        """The :class:`Estimate` named ``name`` (a plant parameter or ``noise_std_<channel>``)."""
        for e in self.parameters + self.noise_std:
            if e.name == name:
                return e
        raise ValueError(f"no parameter {name!r}; expected one of {[e.name for e in self.parameters + self.noise_std]}")

    def theta(self) -> np.ndarray:
        """The plant's parameter vector (estimates; 1 where not identifiable)."""
        return np.array([e.estimate if e.identifiable else 1.0 for e in self.parameters])

    def summary(self) -> dict:
        """A plain-JSON record of the identification."""
        m = self.model
        return {
            "robot": m.robot.name,
            "level": str(m.level),
            "period_s": m.period,
            "parameters": {e.name: e.summary() for e in self.parameters},
            "noise_std": {e.name: e.summary() for e in self.noise_std},
            "delay_samples": self.delay,
            "delay_negative_log_likelihood": list(self.delay_nll),
            "residual_rms": {
                name: dict(zip(m.channels, map(float, row))) for name, row in zip(self.log_names, self.residual_rms)
            },
            "logs": [
                {"name": n, "samples": c.n_samples, "period_s": c.period, "saturated_rows": list(c.saturated)}
                for n, c in zip(self.log_names, self.checks)
            ],
            "segments": int(self.segments.log.shape[0]),
            "segment_s": self.options.segment,
            "correlation": [[None if not np.isfinite(v) else float(v) for v in row] for row in self.correlation],
            "iterations": self.iterations,
            "converged": self.converged,
        }


def _check_inputs(model: PlantModel, logs, options: FitOptions) -> tuple:
    if not isinstance(model, PlantModel):
        raise ValueError(f"model must be a wmrjax.identify.PlantModel, got {type(model).__name__}")
    if not logs or not all(isinstance(log, Log) for log in logs):
        raise ValueError("logs must be a non-empty list of wmrjax.identify.Log (read them with read_log)")
    nX, nu = model.robot.n_state, model.robot.n_input
    for log in logs:
        if log.posture.shape[1:] != (nX,) or log.command.shape[1:] != (nu,):
            raise ValueError(
                f"log {log.name!r}: {log.posture.shape[1]} measured channel(s) and {log.command.shape[1]} command(s); "
                f"a {model.robot.name} robot has {nX} ({', '.join(model.channels)}) and {nu}"
            )
    if not (options.segment > 0 and math.isfinite(options.segment)):
        raise ValueError(f"options.segment must be a duration > 0 [s], got {options.segment!r}")
    if not isinstance(options.max_delay, int) or options.max_delay < 0:
        raise ValueError(f"options.max_delay must be a whole number of samples >= 0, got {options.max_delay!r}")
    length = int(round(options.segment / model.period))
    if length < 2:
        raise ValueError(
            f"options.segment = {options.segment} s is less than two periods of {model.period} s; a segment needs two samples"
        )
    return tuple(check_log(log, model.period, model.input_limit) for log in logs), length


def identify(model: PlantModel, logs: list, options: FitOptions = FitOptions()) -> Identification:
    """Identify the plant's geometry and input scales (and the measurement noise, and an input
    delay) from logs, by maximum likelihood, with standard errors and 95 % intervals.

    Args:
      model: what is known (:class:`PlantModel`: robot type, level, nominal geometry, limits,
        period).
      logs: one or more :class:`wmrjax.identify.Log` of that robot (:func:`wmrjax.identify.read_log`).
      options: :class:`FitOptions`.

    Returns:
      :class:`Identification`.

    Raises:
      ValueError: a log :func:`wmrjax.identify.check_log` refuses, of another robot's width, or
        options out of range (before anything compiles).
    """
    checks, length = _check_inputs(model, logs, options)
    names, start = model.names, options.max_delay
    free = tuple(range(len(names)))
    fits, why = [], {}
    seg0 = cut(model, logs, length, start, 0)
    for d in range(options.max_delay + 1):
        seg = with_delay(logs, seg0, d)
        fit = _fit(model, free, seg, options)
        lost = not_identifiable(names, free, fit)
        if lost:  # held at nominal, the rest fitted again
            why.update(lost)
            free_d = tuple(i for i in free if i not in lost)
            keep = [k for k, i in enumerate(free) if i in free_d]
            fit = _fit(model, free_d, seg, options, theta=fit.state.theta[keep])
            free = free_d
        fits.append((fit, seg, free))
    nll = tuple(f.nll for f, _, _ in fits)
    delay = int(np.argmin(nll))
    fit, seg, free = fits[delay]
    return _report(model, logs, checks, options, fit, seg, free, why, delay, nll)


def _report(model, logs, checks, options, fit: _Fit, seg, free, why, delay, nll) -> Identification:
    names = model.names
    F = _reduced_information(fit.normal)
    cov = np.linalg.inv(F) if F.size else F
    se = np.sqrt(np.maximum(np.diagonal(cov), 0.0))
    params = []
    for i, name in enumerate(names):
        if i in free:
            k = free.index(i)
            v, s = float(fit.state.theta[k]), float(se[k])
            params.append(Estimate(name, v, s, (v - Z95 * s, v + Z95 * s), True))
        else:
            params.append(Estimate(name, None, None, None, False, why.get(i, "not fitted")))
    corr = np.full((len(names), len(names)), np.nan)
    if free:
        idx = np.asarray(free)
        corr[np.ix_(idx, idx)] = cov / np.outer(se, se)
    # the noise: se of log(sigma) is 1 / sqrt(2 dof) (the Hessian of the likelihood in log sigma)
    noise = []
    for ch, s in zip(model.channels, fit.sigma):
        h = Z95 / math.sqrt(2.0 * fit.dof)
        noise.append(
            Estimate(
                f"noise_std_{ch}",
                float(s),
                float(s / math.sqrt(2.0 * fit.dof)),
                (float(s * math.exp(-h)), float(s * math.exp(h))),
                True,
            )
        )
    return Identification(
        model,
        tuple(params),
        tuple(noise),
        delay,
        nll,
        checks,
        tuple(log.name for log in logs),
        _rms_per_log(fit.state.r, seg, len(logs)),
        seg,
        seg.measured - fit.state.r,
        corr,
        fit.iterations,
        fit.converged,
        options,
    )


def prediction_error(ident: Identification, logs: list, theta=None) -> np.ndarray:
    """(n_logs, n_X) root-mean-square error of predicting ``logs`` (e.g. held out of the fit) over
    segments of the fit's length, each from its fitted initial state, with the plant's
    parameters held at ``theta`` (default: the identified ones; ``np.ones`` for the nominal plant).

    Raises:
      ValueError: logs that :func:`wmrjax.identify.check_log` refuses.
    """
    model, options = ident.model, ident.options
    _, length = _check_inputs(model, logs, options)
    theta = ident.theta() if theta is None else np.asarray(theta, float)
    seg = cut(model, logs, length, options.max_delay, ident.delay)
    free = tuple(range(len(model.names)))
    fit = _fit(model, free, seg, options, theta=theta, fit_plant=False)
    return _rms_per_log(fit.state.r, seg, len(logs))


def _rms_per_log(r, seg: Segments, n_logs: int) -> np.ndarray:
    """(n_logs, n_X) root-mean-square residual of each log's samples (padding masked out)."""
    out = []
    for j in range(n_logs):
        on = seg.log == j
        out.append(np.sqrt(np.einsum("gs,gsi->i", seg.mask[on], r[on] ** 2) / max(np.sum(seg.mask[on]), 1.0)))
    return np.stack(out)
