"""Synthetic robot logs from an independent integration: the kinematic models (paper eqs 5, 8 and
Table 2) written out here and integrated by SciPy's DOP853 over each held command, never by
:func:`wmrjax.simulate`; the tests of :mod:`wmrjax.identify` and ``benchmarks/identify.py`` fit them.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from wmrjax.identify import Log


def body(kind: str, X, eta, L):
    """World-frame posture velocity of type ``kind`` (Table 2's Sigma, rotated by R^T(theta))."""
    th = X[2]
    if kind == "(2,0)":
        vb = (0.0, eta[0], eta[1])
    elif kind == "(1,1)":
        b = X[3]
        vb = (0.0, L * np.sin(b) * eta[0], np.cos(b) * eta[0])
    elif kind == "(3,0)":
        vb = tuple(eta)
    else:
        raise ValueError(kind)
    c, s = np.cos(th), np.sin(th)
    return np.array([c * vb[0] - s * vb[1], s * vb[0] + c * vb[1], vb[2]])


DELTA_M = {"(2,0)": 2, "(1,1)": 1, "(3,0)": 3}
DELTA_S = {"(2,0)": 0, "(1,1)": 1, "(3,0)": 0}


def field(kind, level, L, applied):
    dm, ds = DELTA_M[kind], DELTA_S[kind]
    n = 3 + ds

    def f(t, z):
        if level == "velocity":
            u = applied
        else:
            u = z[n:]
        xi = body(kind, z[:n], u[:dm], L)
        dz = np.concatenate([xi, u[dm:]])
        return dz if level == "velocity" else np.concatenate([dz, applied])

    return f


def commands(kind: str, level: str, n: int, period: float, rng) -> np.ndarray:
    """(n, n_input) smooth, exciting commands: a constant plus two random sinusoids per input."""
    nu = DELTA_M[kind] + DELTA_S[kind]
    t = np.arange(n) * period
    if level == "velocity":
        base = {"(2,0)": [0.8, 0.0], "(1,1)": [0.8, 0.0], "(3,0)": [0.3, 0.5, 0.0]}[kind]
        amp = {"(2,0)": [0.3, 0.6], "(1,1)": [0.3, 0.5], "(3,0)": [0.3, 0.3, 0.5]}[kind]
    else:
        base, amp = [0.0] * nu, {"(2,0)": [0.6, 1.0], "(1,1)": [0.6, 1.0], "(3,0)": [0.5, 0.5, 1.0]}[kind]
    u = np.empty((n, nu))
    for i in range(nu):
        w = rng.uniform(0.3, 1.5, 2)
        ph = rng.uniform(0, 2 * np.pi, 2)
        u[:, i] = base[i] + amp[i] * (np.sin(w[0] * t + ph[0]) + 0.5 * np.sin(w[1] * t + ph[1])) / 1.5
    return u


def make_log(
    kind: str,
    level: str,
    *,
    L: float,
    geometry_scale: float,
    input_scale,
    noise_std,
    n: int,
    period: float,
    seed: int,
    x0=None,
    name: str = "synthetic",
    limit=None,
    noise_seed: int | None = None,
) -> Log:
    """One log of ``n`` samples: the true plant (L times ``geometry_scale``, inputs times
    ``input_scale``, clipped at ``limit``) driven by held commands, its posture measured with
    Gaussian noise of std ``noise_std`` per channel. ``seed`` draws the commands (and, without
    ``noise_seed``, the noise too); ``noise_seed`` draws the noise alone (the same commands, a new
    noise: a parametric bootstrap's replicate)."""
    rng = np.random.default_rng(seed)
    ds = DELTA_S[kind]
    nu = DELTA_M[kind] + ds
    cmd = commands(kind, level, n, period, rng)
    n_x = 3 + ds
    z = np.zeros(n_x + (nu if level == "torque" else 0)) if x0 is None else np.asarray(x0, float)
    if level == "torque" and x0 is None:
        z[n_x] = 0.8 if kind != "(3,0)" else 0.3  # moving forward at the start
    scale = np.broadcast_to(np.asarray(input_scale, float), (nu,))
    lim = np.full(nu, np.inf) if limit is None else np.asarray(limit, float)
    states = [z]
    for k in range(n - 1):
        applied = np.clip(scale * cmd[k], -lim, lim)
        sol = solve_ivp(
            field(kind, level, L * geometry_scale, applied), (0.0, period), z, method="DOP853", rtol=1e-12, atol=1e-12
        )
        z = sol.y[:, -1]
        states.append(z)
    X = np.asarray(states)[:, :n_x]
    sd = np.broadcast_to(np.asarray(noise_std, float), (n_x,))
    noise_rng = rng if noise_seed is None else np.random.default_rng([seed, noise_seed])
    meas = X + noise_rng.normal(size=X.shape) * sd
    meas[:, 2] = np.arctan2(np.sin(meas[:, 2]), np.cos(meas[:, 2]))  # a robot logs a wrapped heading
    return Log(name, np.arange(n) * period, meas, cmd)
