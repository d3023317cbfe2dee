r"""Gains of the linear error dynamics: one representation, Hurwitz coefficients.

Under a linearizing law every output error obeys
:math:`\tilde Y^{(r)} + \sum_{j<r} k_j \tilde Y^{(j)} = 0` (eq 13 for r = 2, eq 49 with
the errata sign for any r). :class:`Gains` stores exactly these coefficients ``k`` per
output, shape (m, r), and nothing else; the constructors build them from

* real poles at :math:`-\lambda_j` (:meth:`Gains.from_poles`; the paper's choice, e.g. a
  double pole at -1 in §6.1: ``k = (1, 2)``);
* second-order factors :math:`s^2 + 2\zeta\omega s + \omega^2` (natural frequency
  :math:`\omega`, damping :math:`\zeta`: real or complex pole pairs), times
  :math:`(s + \lambda)` when r is odd (:meth:`Gains.from_damping`).

Every consumer (the laws, :func:`wmrjax.linearize.companion`, the certificates, the
reference-model state of eq 14) reads ``coeffs``; pole-based reports come from
:meth:`Gains.poles`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax._validate import check_finite, check_number, check_positive, concrete


def monic_coefficients(poles):
    r"""Coefficients of :math:`\prod_j (s + \lambda_j) = s^r + \sum_{j<r} k_j s^j`.

    Args:
      poles: (..., r) positive reals :math:`\lambda_j` (closed-loop poles at :math:`-\lambda_j`).

    Returns:
      (..., r) array ``k`` with ``k[..., j]`` the coefficient of ``s^j``: Hurwitz by
      construction. For r = 2: ``k = (l1 l2, l1 + l2)`` as in eq (13).
    """
    r = poles.shape[-1]
    c = [jnp.ones_like(poles[..., 0])]  # highest power first, start from "1"
    for j in range(r):
        lam = poles[..., j]
        new = [c[0]]
        for i in range(1, len(c)):
            new.append(c[i] + lam * c[i - 1])
        new.append(lam * c[-1])
        c = new
    return jnp.stack(c[::-1][:r], axis=-1)  # ascending powers, without the leading 1


def _polymul(a, b):
    """Product of two polynomials given as coefficient lists, highest power first."""
    out = [0.0 * a[0]] * (len(a) + len(b) - 1)
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            out[i + j] = out[i + j] + x * y
    return out


def damping_coefficients(omega, zeta, lam=None):
    r"""Coefficients of :math:`\prod_k (s^2 + 2\zeta_k\omega_k s + \omega_k^2)\,(s + \lambda)`.

    Args:
      omega: (..., q) natural frequencies [rad/s], > 0.
      zeta: (..., q) dampings, > 0.
      lam: optional (...,) real pole magnitude for odd r.

    Returns:
      (..., r) coefficients, r = 2 q (+ 1 with ``lam``), ascending powers.
    """
    omega, zeta = jnp.asarray(omega), jnp.asarray(zeta)
    poly = [jnp.ones_like(omega[..., 0]) if omega.shape[-1] else jnp.ones_like(jnp.asarray(lam))]
    for k in range(omega.shape[-1]):
        om, ze = omega[..., k], zeta[..., k]
        poly = _polymul(poly, [jnp.ones_like(om), 2.0 * ze * om, om * om])
    if lam is not None:
        lam = jnp.asarray(lam)
        poly = _polymul(poly, [jnp.ones_like(lam), lam])
    return jnp.stack(poly[1:][::-1], axis=-1)


class Gains(NamedTuple):
    r"""Hurwitz coefficients of every output's error polynomial (a pytree: vmap/grad it).

    Attributes:
      coeffs: (m, r); ``coeffs[i, j]`` multiplies :math:`d^j\tilde Y_i/dt^j` (eq 49 errata).
    """

    coeffs: jnp.ndarray

    @property
    def shape(self):
        """The number of outputs m and the relative degree r, as the pair ``(m, r)``."""
        return tuple(jnp.shape(self.coeffs))

    @classmethod
    def from_poles(cls, poles, m: int | None = None, r: int | None = None) -> "Gains":
        """Real poles at ``-poles``.

        Args:
          poles: (m, r), (r,) or scalar pole magnitudes, > 0 (broadcast to (m, r)).
          m: outputs (with ``r``: the target shape (m, r) a scalar or (r,) ``poles`` broadcasts to).
          r: the relative degree (with ``m``).

        Raises:
          ValueError: a non-positive or non-finite pole, or a shape that does not broadcast.
        """
        check_number("poles", poles, "real pole magnitudes > 0")
        p = jnp.asarray(poles, dtype=jnp.result_type(float))
        if m is not None and r is not None:
            if p.ndim > 2 or (p.ndim >= 1 and p.shape[-1] not in (1, r)) or (p.ndim == 2 and p.shape[0] not in (1, m)):
                raise ValueError(
                    f"poles must be a scalar, ({r},) or ({m}, {r}) (one pole magnitude per output and "
                    f"derivative order, r = {r}), got shape {p.shape}"
                )
            p = jnp.broadcast_to(p, (m, r))
        elif p.ndim != 2:
            raise ValueError(f"poles must be (m, r) unless m and r are given, got shape {p.shape}")
        check_positive("poles (closed-loop poles are at -poles; they must be > 0 for a Hurwitz error dynamics)", p)
        return cls(monic_coefficients(p))

    @classmethod
    def from_damping(cls, omega, zeta, lam=None, m: int | None = None) -> "Gains":
        """Second-order factors (omega, zeta) per output, times (s + lam) for odd r.

        Args:
          omega: (q,) or (m, q) natural frequencies [rad/s], > 0.
          zeta: the dampings, the same shape, > 0 (the paper's double pole at -1 is
            omega = zeta = 1).
          lam: None, scalar or (m,) real pole magnitude (odd r).
          m: number of outputs when omega is (q,).
        """
        om, ze = jnp.atleast_1d(jnp.asarray(omega, float)), jnp.atleast_1d(jnp.asarray(zeta, float))
        check_positive("omega (natural frequencies)", om)
        check_positive("zeta (dampings)", ze)
        if lam is not None:
            check_positive("lam (real pole magnitude)", lam)
        c = damping_coefficients(om, ze, lam)
        if c.ndim == 1:
            if m is None:
                raise ValueError("from_damping needs m (number of outputs) when omega is one-dimensional")
            c = jnp.broadcast_to(c, (m, c.shape[0]))
        return cls(c)

    def check(self, m: int, r: int) -> "Gains":
        """ValueError unless ``coeffs`` is a finite (m, r) array of a Hurwitz polynomial per output."""
        c = concrete(self.coeffs)
        if c is None:
            return self
        if c.shape != (m, r):
            raise ValueError(f"gains.coeffs must have shape ({m}, {r}) (outputs, relative degree), got {c.shape}")
        if np.iscomplexobj(c):  # a complex pole pair is two real coefficients (Gains.from_poles)
            raise ValueError(
                f"gains.coeffs must be real (the coefficients of real polynomials), got dtype {c.dtype}; "
                "give complex closed-loop poles with Gains.from_damping (natural frequency and damping)"
            )
        check_finite("gains.coeffs", c)
        bad = [i for i in range(m) if not np.all(np.roots(np.concatenate([[1.0], c[i, ::-1]])).real < 0)]
        if bad:
            raise ValueError(
                f"gains.coeffs of outputs {bad} are not Hurwitz (closed-loop poles "
                f"{self.poles()[bad[0]].tolist()}); the error dynamics would not converge"
            )
        return self

    def poles(self) -> np.ndarray:
        """(m, r) complex closed-loop poles (roots of each output's polynomial); concrete values only."""
        c = np.asarray(self.coeffs)
        return np.stack([np.sort_complex(np.roots(np.concatenate([[1.0], row[::-1]]))) for row in c])

    def is_double_pole(self, value: float = 1.0, rtol: float = 1e-12) -> bool:
        """True iff every output's polynomial is :math:`(s + value)^2` (concrete coefficients; r = 2)."""
        c = concrete(self.coeffs)
        return (
            c is not None
            and c.ndim == 2
            and c.shape[1] == 2
            and bool(np.allclose(c, [value * value, 2.0 * value], rtol=rtol, atol=0.0))
        )

    def cascade_pole(self):
        r"""For r = 2, :math:`\Lambda_1` of the cascade :math:`\dot{\tilde z} + \Lambda_1 \tilde z = \tilde\sigma`,
        :math:`\dot{\tilde\sigma} + \Lambda_2\tilde\sigma = 0` (eqs 12-14): the slower real root, (m,).

        NaN for an output whose poles are complex (no real cascade exists).
        """
        k0, k1 = self.coeffs[:, 0], self.coeffs[:, 1]
        disc = k1 * k1 - 4.0 * k0
        pos = disc > 0
        root = jnp.where(
            pos, jnp.sqrt(jnp.where(pos, disc, 1.0)), 0.0
        )  # double where: finite gradients at a double pole
        return jnp.where(disc >= 0, 0.5 * (k1 - root), jnp.nan)

    time_varying = False  # a class constant, not a pytree leaf

    def coeffs_at(self, t):
        """The (m, r) coefficients at time t [s]: constant gains ignore t."""
        del t
        return self.coeffs

    def coefficient_samples(self):
        """(S, m, r) coefficients at the times that define them: the constant gains once (S = 1)."""
        return self.coeffs[None]


def _hermite_log(times, values, t):
    r"""C^1 piecewise-cubic Hermite interpolation of ``log(values)`` at ``t``, exponentiated.

    Knot slopes are the three-point (non-uniform) finite differences, one-sided at the ends;
    outside ``[times[0], times[-1]]`` the value is held. Positive knot values give positive
    values everywhere.

    Args:
      times: (K,) strictly increasing knot times [s], K >= 2.
      values: (K, ...) positive knot values.
      t: scalar time [s].
    """
    y = jnp.log(values)
    h = times[1:] - times[:-1]  # (K-1,)
    hb = h.reshape((-1,) + (1,) * (y.ndim - 1))
    delta = (y[1:] - y[:-1]) / hb  # secant slopes
    if y.shape[0] > 2:
        interior = (hb[1:] * delta[:-1] + hb[:-1] * delta[1:]) / (hb[:-1] + hb[1:])
        d = jnp.concatenate([delta[:1], interior, delta[-1:]])
    else:
        d = jnp.concatenate([delta, delta])
    i = jnp.clip(jnp.searchsorted(times, jax.lax.stop_gradient(t), side="right") - 1, 0, times.shape[0] - 2)
    s = jnp.clip((t - times[i]) / h[i], 0.0, 1.0)
    s2, s3 = s * s, s * s * s
    val = (
        (2 * s3 - 3 * s2 + 1) * y[i]
        + (s3 - 2 * s2 + s) * h[i] * d[i]
        + (-2 * s3 + 3 * s2) * y[i + 1]
        + (s3 - s2) * h[i] * d[i + 1]
    )
    return jnp.exp(val)


class GainSchedule(NamedTuple):
    r"""Time-varying gains :math:`\Lambda(t)`: each output's (omega, zeta[, lam]) as a smooth
    function of time (a pytree: vmap/grad it).

    The error polynomial of output i at time t is
    :math:`\prod_k (s^2 + 2\zeta_{ik}(t)\omega_{ik}(t) s + \omega_{ik}(t)^2)\,(s + \lambda_i(t))`
    (the last factor for odd r), as in :meth:`Gains.from_damping`; each parameter is a C^1
    piecewise-cubic Hermite interpolant of its logarithm through the knot values, held
    constant outside ``[times[0], times[-1]]``. Positive knot values therefore give a Hurwitz
    polynomial at every frozen time. Frozen-time Hurwitz is not stability of the time-varying
    error dynamics :math:`\dot{\tilde\zeta} = A(t)\tilde\zeta`; the certificates use its
    transition matrix :math:`\Phi(t, 0)` (:func:`wmrjax.linearize.transition_matrix`), which
    is exact.

    Attributes:
      times: (K,) strictly increasing knot times [s], K >= 2.
      omega, zeta: (K, m, q) natural frequencies [rad/s] and dampings at the knots, > 0.
      lam: (K, m) real pole magnitudes [1/s] (odd r), or None (even r).
    """

    times: jnp.ndarray
    omega: jnp.ndarray
    zeta: jnp.ndarray
    lam: jnp.ndarray | None = None

    time_varying = True

    @property
    def shape(self):
        """The number of outputs m and the relative degree r, as the pair ``(m, r)``."""
        m, q = jnp.shape(self.omega)[-2:]
        return (m, 2 * q + (0 if self.lam is None else 1))

    @classmethod
    def from_damping(cls, times, omega, zeta, lam=None) -> "GainSchedule":
        """A checked schedule from knot values (see the class attributes for the shapes).

        Raises:
          ValueError: fewer than 2 knots, knot times not strictly increasing or not finite or
            traced (under ``jax.jit``), a non-positive parameter, or shapes that disagree.
        """
        ts = concrete(times)
        if ts is None:
            raise ValueError(
                "GainSchedule.from_damping checks its knot times, which must be concrete (NumPy or a "
                "list): build the schedule outside jax.jit / jax.vmap; its omega, zeta and lam may be traced"
            )
        ts = np.asarray(ts, float)
        if ts.ndim != 1 or ts.size < 2:
            raise ValueError(
                f"a gain schedule needs at least 2 knot times (a (K,) array, K >= 2), got shape {ts.shape}"
            )
        if not np.all(np.isfinite(ts)) or np.any(np.diff(ts) <= 0):
            raise ValueError(f"knot times must be finite and strictly increasing [s], got {ts.tolist()}")
        om, ze = jnp.asarray(omega, float), jnp.asarray(zeta, float)
        if om.ndim != 3 or om.shape[0] != ts.size or ze.shape != om.shape:
            raise ValueError(
                f"omega and zeta must both be (K, m, q) = ({ts.size}, m, q) (one value per knot, output "
                f"and second-order factor), got {om.shape} and {ze.shape}"
            )
        check_positive("omega (natural frequencies at the knots)", om)
        check_positive("zeta (dampings at the knots)", ze)
        if lam is not None:
            lam = jnp.asarray(lam, float)
            if lam.shape != om.shape[:2]:
                raise ValueError(f"lam must be (K, m) = {om.shape[:2]}, got {lam.shape}")
            check_positive("lam (real pole magnitudes at the knots)", lam)
        return cls(jnp.asarray(ts), om, ze, lam)

    def damping_at(self, t):
        """``(omega, zeta, lam)`` at time t [s]: (m, q), (m, q) and (m,) or None."""
        om = _hermite_log(self.times, self.omega, t)
        ze = _hermite_log(self.times, self.zeta, t)
        return om, ze, None if self.lam is None else _hermite_log(self.times, self.lam, t)

    def parameters_at(self, t):
        """(m, r) positive parameters at time t [s], per output ordered omega1, zeta1, ..., lam."""
        om, ze, lam = self.damping_at(t)
        out = jnp.stack([om, ze], axis=-1).reshape(om.shape[0], -1)
        return out if lam is None else jnp.concatenate([out, lam[:, None]], axis=-1)

    def coeffs_at(self, t):
        """The (m, r) Hurwitz coefficients at time t [s] (eq 49 with time-varying gains)."""
        return damping_coefficients(*self.damping_at(t))

    def coefficient_samples(self):
        """(K, m, r) coefficients at the knots."""
        return damping_coefficients(self.omega, self.zeta, self.lam)

    def check(self, m: int, r: int) -> "GainSchedule":
        """ValueError unless the schedule is for m outputs of relative degree r, with K >= 2
        strictly increasing knots and positive parameters (concrete values only)."""
        if self.shape != (m, r):
            raise ValueError(
                f"the gain schedule is for (m, r) = {self.shape}, the controller needs ({m}, {r}) "
                "(outputs, relative degree)"
            )
        leaves = [concrete(x) for x in (self.times, self.omega, self.zeta, self.lam) if x is not None]
        if all(v is not None for v in leaves):
            GainSchedule.from_damping(self.times, self.omega, self.zeta, self.lam)
        return self

    def poles(self) -> np.ndarray:
        """(K, m, r) complex closed-loop poles at the knots (concrete values only)."""
        c = np.asarray(self.coefficient_samples())
        return np.stack([Gains(ck).poles() for ck in c])

    def is_double_pole(self, value: float = 1.0, rtol: float = 1e-12) -> bool:
        """Always False: eq (64) is for the constant double pole."""
        del value, rtol
        return False
