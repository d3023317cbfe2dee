r"""Gain parameterisation: Hurwitz error polynomials from unconstrained parameters.

The tuned quantity is an unconstrained array ``raw``; positive quantities come from
``softplus`` (dynamax style), so every parameter value gives a Hurwitz polynomial:

* ``"damping"`` (default): per output, :math:`\lfloor r/2\rfloor` second-order factors
  :math:`s^2 + 2\zeta\omega s + \omega^2` (natural frequency :math:`\omega`, damping
  :math:`\zeta`, both > 0: real or complex pole pairs) times :math:`(s + \lambda)` when r is
  odd. The paper's double pole at -1 is :math:`\omega = \zeta = 1`. Unlike real poles, whose
  loss is symmetric under swapping :math:`\lambda_1, \lambda_2` (so gradient descent from the
  paper's double pole never leaves :math:`\lambda_1 = \lambda_2`), this reaches every Hurwitz
  polynomial.
* ``"poles"``: r real poles at :math:`-\lambda_j`, :math:`\lambda_j > 0`.

Shared across axes (one polynomial for every output) or per axis; frozen entries are held
by ``stop_gradient``.

A *gain schedule* (``knots``: K >= 2 knot times [s]) gives every one of these parameters a
value per knot: :math:`\Lambda(t)` is a :class:`wmrjax.GainSchedule` (C^1 interpolation of
the parameters' logarithms, Hurwitz at every time; damping parameterization only). At torque
level (relative degree r + 1, odd for the r = 2 types) the damping form is the outer loop's
(omega, zeta) times the Lemma 1 inner loop's real pole ``lambda``: both are tuned together.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax.gains import Gains, GainSchedule, damping_coefficients, monic_coefficients


def softplus_inverse(y):
    """The inverse of softplus: raw with softplus(raw) = y (y > 0), numerically stable."""
    y = jnp.asarray(y)
    return y + jnp.log(-jnp.expm1(-y))


@dataclasses.dataclass(frozen=True)
class GainFamily:
    """Static description of the tuned gains (hashable; not a pytree).

    Attributes:
      m, r: the controller's outputs and relative degree.
      shared: one polynomial for every output (raw shape (r,)) instead of (m, r).
      frozen: flat indices into raw that are not tuned (held by stop_gradient).
      parameterization: "damping" or "poles" (module docstring).
      knots: knot times [s] of a gain schedule (K >= 2, strictly increasing); () for constant gains.
      min_damping: floor of every damping zeta (damping parameterization): zeta = min_damping +
        softplus(raw), a design constraint on how oscillatory the error response may be.
    """

    m: int
    r: int
    shared: bool = True
    frozen: tuple = ()
    parameterization: str = "damping"
    knots: tuple = ()
    min_damping: float = 0.0

    def __post_init__(self):
        if self.knots:
            k = np.asarray(self.knots, float)
            if k.ndim != 1 or k.size < 2 or not np.all(np.isfinite(k)) or np.any(np.diff(k) <= 0):
                raise ValueError(f"knots must be >= 2 finite, strictly increasing times [s], got {list(self.knots)}")
            if self.parameterization != "damping":
                raise ValueError(
                    "a gain schedule needs the damping parameterization (its frozen-time polynomials "
                    f"stay Hurwitz as the parameters move), got {self.parameterization!r}"
                )

    @property
    def per_time_shape(self):
        """The shape of the parameters at one time."""
        return (self.r,) if self.shared else (self.m, self.r)

    @property
    def shape(self):
        """The parameters' shape (knots first for a schedule)."""
        return ((len(self.knots),) if self.knots else ()) + self.per_time_shape

    @property
    def size(self) -> int:
        """Number of tuned parameters (frozen ones included)."""
        return int(np.prod(self.shape))

    def kinds(self):
        """raw-shaped array of parameter kinds: "rate" (omega, real poles; [1/s]) or "damping" (zeta)."""
        one = np.asarray(["damping" if n.startswith("zeta") else "rate" for n in self.names()])
        return np.broadcast_to(one, self.shape)

    def names(self):
        """Names of the r positive parameters of one output."""
        if self.parameterization == "poles":
            return [f"lambda{j + 1}" for j in range(self.r)]
        return sum(([f"omega{k + 1}", f"zeta{k + 1}"] for k in range(self.r // 2)), []) + (["lambda"] * (self.r % 2))

    def positive(self, raw):
        """The positive parameters, raw shape, frozen entries held."""
        if self.frozen:
            mask = np.zeros(int(np.prod(self.shape)), bool)
            mask[list(self.frozen)] = True
            raw = jnp.where(jnp.asarray(mask.reshape(self.shape)), jax.lax.stop_gradient(raw), raw)
        return jax.nn.softplus(raw) + self._floor()

    def _floor(self):
        """raw-shaped floor added after softplus: min_damping on the dampings, 0 elsewhere."""
        return np.where(self.kinds() == "damping", self.min_damping, 0.0)

    def raw_from_positive(self, positive):
        """The unconstrained parameters giving these positive ones (each above its floor)."""
        return softplus_inverse(jnp.asarray(positive) - self._floor())

    def _coeffs_one(self, p):
        """k_0 .. k_{r-1} (coefficients of d^j/dt^j) of one output from its positive parameters."""
        if self.parameterization == "poles":
            return monic_coefficients(p)
        q = self.r // 2
        return damping_coefficients(p[0 : 2 * q : 2], p[1 : 2 * q : 2], p[-1] if self.r % 2 else None)

    def coefficients(self, raw):
        """(m, r) coefficients of the error polynomial of each output ((K, m, r) at the knots of a schedule)."""
        p = self.positive(raw)
        one = (lambda q: self._coeffs_one(q)[None]) if self.shared else jax.vmap(self._coeffs_one)  # (1 or m, r)
        c = jax.vmap(one)(p) if self.knots else one(p)
        return jnp.broadcast_to(c, ((len(self.knots),) if self.knots else ()) + (self.m, self.r))

    def gains(self, raw):
        """:class:`wmrjax.Gains` (Hurwitz coefficients) for the controller, or a :class:`wmrjax.GainSchedule`."""
        if not self.knots:
            return Gains(self.coefficients(raw))
        K, q = len(self.knots), self.r // 2
        p = jnp.broadcast_to(self.positive(raw).reshape((K, -1, self.r)), (K, self.m, self.r))
        lam = p[..., -1] if self.r % 2 else None
        return GainSchedule(jnp.asarray(self.knots, p.dtype), p[..., 0 : 2 * q : 2], p[..., 1 : 2 * q : 2], lam)

    def closed_loop_poles(self, raw):
        """Complex closed-loop poles per output, as [[re, im], ...] lists (for reports; per knot for a schedule)."""

        def one(c):
            return [[[float(z.real), float(z.imag)] for z in np.roots(np.concatenate([[1.0], row[::-1]]))] for row in c]

        c = np.asarray(self.coefficients(raw))
        return [one(ck) for ck in c] if self.knots else one(c)

    def init(self, poles):
        """The raw parameters giving every output the real poles -poles (scalar: a repeated pole).

        Raises:
          ValueError: non-positive or non-finite poles, a bad shape or frozen index.
        """
        p = np.asarray(poles, dtype=float)
        if not np.all(np.isfinite(p)) or np.any(p <= 0):
            raise ValueError(f"initial pole magnitudes must be finite and > 0 (poles at -p), got {p.tolist()}")
        if p.ndim == 0:
            p = np.full(self.r, float(p))
        if p.shape != (self.r,):
            raise ValueError(f"initial poles must be a scalar or ({self.r},), got shape {p.shape}")
        if self.parameterization == "poles":
            one = p
        else:
            one = []
            for k in range(self.r // 2):
                a, b = p[2 * k], p[2 * k + 1]
                one += [np.sqrt(a * b), (a + b) / (2.0 * np.sqrt(a * b))]
            one += list(p[-1:]) if self.r % 2 else []
            one = np.asarray(one)
        full = np.broadcast_to(one, self.shape)  # a schedule starts constant
        for i in self.frozen:
            if not 0 <= i < full.size:
                raise ValueError(f"frozen index {i} out of range for {full.size} tuned parameters")
        if np.any(full - self._floor() <= 0):
            raise ValueError(
                f"initial dampings {np.unique(full[self.kinds() == 'damping']).tolist()} must exceed "
                f"min_damping = {self.min_damping}"
            )
        return self.raw_from_positive(full)
