r"""The saturation-free radius: from which initial errors the nominal closed loop never asks
its actuators for more than their limits over [0, T] (issue 54, item 2).

Inside that ball a saturating plant never saturates, so its closed loop *is* the nominal one
and every nominal certificate holds for it exactly: the problem's radius under input limits is
the smaller of this radius and the exact map's.

On the nominal loop the output error is :math:`\tilde\zeta(t) = e^{At} P s` (the slice's
initial error s), the state is :math:`\Psi^{-1}(\zeta_{ref}(t) + \tilde\zeta(t))` on the
reference's branch, and the plant's command is the law's input there: a known function
:math:`u(t, s)` (velocity level: the wheel velocities; torque level: their rates). The bound:

* [0, T] is covered by time boxes :math:`[t_c - h, t_c + h]`; in a box, :math:`t = t_c + h\tau`
  with :math:`\tau \in [-1, 1]` a symbol of an affine evaluation
  (:mod:`wmrjax.certify.affine`) of the reference's jet, and :math:`s = \rho\,\varepsilon`
  with :math:`\varepsilon` in the unit ball; a sampled path's boxes are cut at its knots and
  each encloses its own piece's polynomial (:func:`wmrjax.references.time_boxes`, :func:`jet_boxes`);
* :math:`e^{At} = e^{At_c} e^{A h\tau}`, so :math:`\tilde\zeta = e^{At_c}P s` plus at most
  :math:`\|e^{At_c}\|_{row\,i}(e^{\|A\| h} - 1)\rho` per entry (an error term);
* the command's affine enclosure over the box and the ball must lie within the limits; the
  largest such :math:`\rho` per box is found by bisection (the enclosure grows with
  :math:`\rho`: a box certified at :math:`\rho` is certified below it), and the boxes with the
  smallest radius are halved for a few rounds;
* the radius is the minimum over the boxes: a **proved** lower bound. An **attained** upper
  bound comes from point evaluations of :math:`u(t, s)` on rays at t = 0 and at the worst
  boxes' centres.

The enclosure is first-order tight in :math:`\rho` and h; it loses where the command is
strongly nonlinear over the ball (near the singular set, where :math:`\det K` is small), which
the ratio lower / upper reports. On a two-dimensional slice (the position slice) the limiting
boxes are bounded again over a cover of the disc by small boxes (:func:`disc_cover`), whose
remainders shrink with the square of their size, until the proved radius is within
:data:`PIECE_GAP` of the attained one.
"""

from __future__ import annotations

import concurrent.futures
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _math
from wmrjax.certify import affine, interval
from wmrjax.certify.exact_map import Slice, slice_basis
from wmrjax.certify.lemma2 import check_dynamic
from wmrjax.controllers import Space, Task, place
from wmrjax.controllers.law import DET_FLOOR
from wmrjax.references import box_pieces, enclose_over_pieces, time_boxes
from wmrjax.simulate import fixed_blocks

BOX_BLOCK = 256
"""Time boxes evaluated per compiled call (over the whole ball)."""
PIECE_BLOCK = 32
"""Time boxes evaluated per compiled call over a cover's pieces (each box costs as many
enclosures as the cover has pieces)."""
SEARCH_COMPILE = {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": False}
"""XLA's full optimizer (its default level), whatever the process's own setting: the box search
runs this program about 130 times a slice (bisection steps times refinement rounds), so its run
outweighs its compile (the circle of the tests, 821 boxes, 2 cores: 7 s a slice after 62 s of
compiling, against 28 s after 50 s at level 0). XLA:CPU's legacy elemental emitters, not its MLIR
fusion emitters: the enclosure's thousands of small fusions compile a third faster (45 -> 31 s)
to the same radii (``wmrjax certify steered_21``: 122.5 -> 101.1 s, 2026-12-01, 2 cores)."""


class SaturationFreeRadius(NamedTuple):
    """Result of :func:`saturation_free_radius` (radii in the slice's output-error units).

    Attributes:
      lower_bound: proved: from every initial error of the slice with norm below it, every
        command of the nominal loop over [0, T] is within the limits.
      upper_bound: attained: an initial error of this norm whose nominal command exceeds a limit
        at ``worst_time`` (inf if none was found on the rays tried).
      worst_error: (n,) that initial error (None if none).
      worst_time: its time [s] (None if none).
      boxes: the number of time boxes of the final cover.
    """

    lower_bound: float
    upper_bound: float
    worst_error: np.ndarray | None
    worst_time: float | None
    boxes: int


def command(ctrl, params, jet, error):
    """The nominal loop's plant command at the reference jet ``jet`` ((r + 1, m)) and output
    error ``error`` ((r m,)): the state on the reference's branch, the law's input (49) with
    its error equal to ``error`` (the nominal loop's), and the plant input (velocity level) or
    its rate (torque level)."""
    return placed_command(ctrl, params, jet, error)[1]


def placed_command(ctrl, params, jet, error):
    """``(z, u)``: :func:`command` and the law's state it is computed at (one placement for a
    caller that needs both)."""
    r, m, law, g = ctrl.relative_degree, ctrl.m, ctrl.law, params.geometry
    err = error.reshape(r, m)
    z = place(ctrl, params, error, Space.OUTPUT, Task.POSTURE, ctrl.reference_branch(params), jet=jet)
    coeffs = params.gains.coeffs_at(0.0)
    w = jet[r]
    for j in range(r):
        w = w - coeffs[:, j] * err[j]
    _, a, K = law.jet(z, g)
    return z, law.plant_control(z, preconditioned_solve(K, w - a), g)


PRECONDITIONED_STEPS = 6
"""Steps of :func:`preconditioned_solve`'s refinement."""


def preconditioned_solve(K, b):
    r""":math:`U = K^{-1}b` as the law computes it (adjugate over :math:`\det K`, clamped at
    :data:`wmrjax.controllers.law.DET_FLOOR`), refined for enclosures.

    :math:`U = Mb + (I - MK)U` holds for *every* matrix M. With M the inverse of K's anchor
    (:func:`wmrjax.certify.interval.anchor`: K itself at a point, where the refinement changes
    nothing but rounding; the centre of K's enclosure over a box), :math:`I - MK` is small over
    the box and each step replaces the wide enclosure of the adjugate quotient (its
    determinant's enclosure loses the correlation of K's entries) by a tight first-order one.

    Args:
      K: (m, m) the decoupling matrix, m <= 3.
      b: (m,) the right-hand side.
    """
    num, det = _math.adjugate_solve(K, b)
    U = num / _math.safe_divisor(det, DET_FLOOR)
    Kc = interval.anchor(K)
    eye = jnp.eye(K.shape[0], dtype=K.dtype)
    cols = [_math.adjugate_solve(Kc, e) for e in eye]
    M = jnp.stack([n / d for n, d in cols], axis=1)
    residual = eye - M @ K
    for _ in range(PRECONDITIONED_STEPS):
        U = M @ b + residual @ U
    return U


def _padded(P):
    """The slice basis padded with zero columns to n: one compiled program for every slice."""
    n, k = P.shape
    return jnp.concatenate([P, jnp.zeros((n, n - k), P.dtype)], axis=1)


@functools.partial(jax.jit, static_argnums=0)
def jet_boxes(ctrl, params, t_c, h, piece=None):
    """The reference jet ((r + 1, m)) over each time box ``[t_c - h, t_c + h]``, affine in the
    time symbol (the last of n + 1 symbols: the n ball symbols of :func:`_box_fits` come first).

    ``piece`` ((B,) int, or None): each box's piece of a reference with breakpoints, whose own
    polynomial is enclosed (:meth:`wmrjax.references.Reference.piece`): sound only for a box
    inside its piece's interval (:func:`wmrjax.references.time_boxes` cuts them so). Across a knot the reference
    itself straddles two pieces, and the hull of their coefficients and start times, correlated
    in the jet, made its remainder unbounded (the car's 15 knots: a saturation-free radius 0)."""
    r, n = ctrl.relative_degree, ctrl.relative_degree * ctrl.m

    def one(tc, hh, j):
        t = affine.symbols(tc, jnp.zeros(n + 1).at[n].set(hh))
        p = params if j is None else params._replace(reference=params.reference.piece(j))
        # angles modulo 2 pi (a heading across +-pi stays one interval): the command is periodic
        # in them (checked by _check_periodic)
        jet = lambda tt: ctrl.reference_jet(tt, p)[: r + 1]
        return tuple(affine.enclose(jet, t, n_ball=n, angles_mod_2pi=True)[0])

    return jax.vmap(one)(t_c, h, piece)


def box_jets(ctrl, params, breaks, t_c, h, across: bool = False) -> tuple:
    """:func:`jet_boxes` over the boxes ``t_c`` +- ``h`` in blocks of :data:`BOX_BLOCK` (NumPy
    arrays), each pinned to its piece (:func:`wmrjax.references.box_pieces`) where ``breaks`` is not
    None. With ``across``, a box across breakpoints (a controller's period) is the hull of its
    pieces' polynomials, each enclosed over the whole box: at every time of the box the reference
    is one of them (a spline's pieces agree to its degree's order at a knot, so the hull is tight);
    a box past the breakpoints' ends encloses the reference itself."""
    program = lambda *a: jet_boxes(ctrl, params, *a)
    if breaks is None:
        return fixed_blocks(program, (t_c, h), BOX_BLOCK)
    if not across:
        return fixed_blocks(program, (t_c, h, box_pieces(breaks, t_c, h)), BOX_BLOCK)
    pinned = lambda rows, j: (t_c[rows], h[rows]) + (() if j is None else (j,))
    enclose = lambda rows, j: fixed_blocks(program, pinned(rows, j), BOX_BLOCK)
    return enclose_over_pieces(enclose, lambda a, b: _hull(*a, *b), breaks, t_c, h)


def _hull(c1, g1, e1, c2, g2, e2):
    """An affine form (centre, generators, error) holding both forms' values at every value of the
    symbols (the mean's, with the halved differences as error), rounded outward."""
    c, g = 0.5 * (c1 + c2), 0.5 * (g1 + g2)
    spread = 0.5 * np.abs(c1 - c2) + 0.5 * np.sum(np.abs(g1 - g2), axis=-1)
    e = np.maximum(e1, e2) + spread
    # the mean's rounding (half an ulp of each entry) and the sum's: covered by a relative allowance
    scale = np.abs(c1) + np.abs(c2) + np.sum(np.abs(g1) + np.abs(g2), axis=-1)
    return c, g, np.nextafter(e + 1e-15 * scale + 1e-300, np.inf)


def turned(a, phi):
    """Rows of (x, y, ...) outputs seen from axes turned by ``phi``: x and y turned by -phi, the
    rest unchanged (the change of a reference jet, whose angles' offset cancels)."""
    c, s = jnp.cos(phi), jnp.sin(phi)
    x, y = a[..., :1], a[..., 1:2]  # no scatter (.at[].set): the enclosures have no rule for it
    return jnp.concatenate([c * x + s * y, c * y - s * x, a[..., 2:]], axis=-1)


def rotated(ctrl, jet, error, phi):
    """The reference jet and the output error seen from axes turned by ``phi`` (the output point's
    coordinates of every order turned by -phi, angle outputs less phi)."""
    mask = np.zeros(jet.shape)
    for i in ctrl.law.extension.angle_outputs:
        mask[0, i] = 1.0
    err = turned(error.reshape(ctrl.relative_degree, ctrl.m), phi).reshape(-1)
    return turned(jet, phi) - phi * mask, err


def reference_heading(ctrl, params, jet_centre):
    """The reference's heading at a box's centre [rad] (its velocity's direction plus the offset)."""
    return jnp.arctan2(jet_centre[1, 1], jet_centre[1, 0]) + params.reference.heading_offset


def turns_alike(ctrl, params, t_final: float, seed: int = 0) -> bool:
    """Whether the law's command is unchanged when the reference and the error are seen from
    turned axes (every law of the paper is: the models are invariant under planar rotations;
    a gain that differs between x and y breaks it). Checked at random times, errors and angles."""
    rng = np.random.default_rng(seed)
    r, n = ctrl.relative_degree, ctrl.relative_degree * ctrl.m
    for t, phi in zip(rng.uniform(0.0, t_final, 4), rng.uniform(-np.pi, np.pi, 4)):
        jet = ctrl.reference_jet(t, params)[: r + 1]
        err = jnp.asarray(0.05 * rng.normal(size=n))
        a = np.asarray(command(ctrl, params, jet, err))
        b = np.asarray(command(ctrl, params, *rotated(ctrl, jet, err, phi)))
        if not np.allclose(a, b, rtol=1e-8, atol=1e-8):
            return False
    return True


class Cover(NamedTuple):
    r"""Pieces whose union contains the slice's unit ball: piece j is :math:`c_j + H_j\varepsilon`
    in the slice's coordinates (padded to n), with :math:`\varepsilon` in the unit ball (``ball``)
    or in :math:`[-1, 1]^n`. A point of the ball of radius :math:`\rho` is :math:`\rho` times a
    point of some piece, so a command enclosed within the limits over every piece is within them
    over the ball.

    Attributes:
      centres: (Q, n) the pieces' centres.
      axes: (Q, n, n) their generators (columns beyond the slice's k are zero).
      sizes: (Q,) a bound on the norm of every point of each piece (for the error term of
        :math:`e^{A(t - t_c)}`).
      ball: whether the symbols lie in the unit ball (else a box).
    """

    centres: np.ndarray
    axes: np.ndarray
    sizes: np.ndarray
    ball: bool


def whole_ball(n: int) -> Cover:
    """The ball itself, one piece (the cover of every slice without a finer one)."""
    return Cover(np.zeros((1, n)), np.eye(n)[None], np.ones(1), True)


DISC_RINGS = (0.15, 0.3, 0.45, 0.6, 0.75, 0.9, 1.0)
"""Radii of the disc cover's rings (:func:`disc_cover`): a square inside the first, then rings."""
DISC_SECTORS = (8, 12, 16, 24, 28, 32)
"""Sectors of each ring (121 pieces with the square)."""


def disc_cover(n: int, rings=DISC_RINGS, sectors=DISC_SECTORS) -> Cover:
    r"""A cover of a 2-dimensional slice's unit disc (the position slice) by boxes: the square of
    half-width ``rings[0]`` (it contains the disc of that radius), and, for each ring
    :math:`[r_0, r_1]` cut into q sectors of half-angle :math:`\delta = \pi / q`, the rectangle
    along each sector's mid-direction u (and v, u turned by 90 degrees) that contains it: a point
    :math:`r(\cos\phi\,u + \sin\phi\,v)` with :math:`r \in [r_0, r_1]`,
    :math:`|\phi| \le \delta` has u-coordinate in :math:`[r_0\cos\delta, r_1]` and
    v-coordinate within :math:`r_1\sin\delta`. The rectangles reach
    :math:`r_1\sqrt{1 + \sin^2\delta}` from the origin (0.5 % beyond the disc for the default's outer 32 sectors):
    what the cover costs the first-order part, against a remainder of second order in a piece's
    size (the default's pieces are 0.15-0.3 across, against the disc's 2).

    Args:
      n: the padded dimension (the slice's two coordinates come first).
      rings: increasing radii ending at 1.
      sectors: sectors per ring (``len(rings) - 1`` of them, each >= 3).
    """
    rings, sectors = tuple(float(r) for r in rings), tuple(int(q) for q in sectors)
    if len(sectors) != len(rings) - 1 or rings[-1] != 1.0 or np.any(np.diff(rings) <= 0) or min(sectors, default=3) < 3:
        raise ValueError(
            f"a disc cover needs increasing rings ending at 1 and >= 3 sectors per ring, got {rings}, {sectors}"
        )
    cs, hs = [np.zeros(2)], [rings[0] * np.eye(2)]
    for r0, r1, q in zip(rings[:-1], rings[1:], sectors):
        d = np.pi / q
        for j in range(q):
            u = np.array([np.cos(2 * d * j), np.sin(2 * d * j)])
            v = np.array([-u[1], u[0]])
            a, b = 0.5 * (r1 - r0 * np.cos(d)), r1 * np.sin(d)
            cs.append(0.5 * (r0 * np.cos(d) + r1) * u)
            hs.append(np.stack([a * u, b * v], axis=1))
    q = len(cs)
    centres, axes = np.zeros((q, n)), np.zeros((q, n, n))
    centres[:, :2], axes[:, :2, :2] = np.array(cs), np.array(hs)
    sizes = np.linalg.norm(centres, axis=1) + np.linalg.norm(axes, axis=1).sum(axis=1)
    return Cover(centres, axes, sizes * (1 + 1e-12), False)


@functools.partial(jax.jit, static_argnums=(0, 1, 2), compiler_options=SEARCH_COMPILE)
def _box_fits(ctrl, turn: bool, ball: bool, params, P, limit, cover, jc, jg, je, t_c, h, rho):
    """Per time box: does the enclosure of the command over the box and every piece of ``cover``
    (centres, axes, sizes: :class:`Cover`, whose ``ball`` is the static ``ball``) at radius rho
    fit? With ``turn``, seen from axes along the reference's heading at the box's centre (the
    heading then stays away from atan2's cut at +-pi inside the box; the command is the same:
    :func:`turns_alike`)."""
    A = ctrl.error_matrix(params.gains)
    growth = jnp.expm1(_math.spectral_norm(A) * h)
    n = P.shape[0]

    def one(jet, tc, g, rh):
        E = _math.expm_small(A * tc)
        phi = reference_heading(ctrl, params, jet.c) if turn else 0.0
        fn = lambda j, e: command(ctrl, params, *rotated(ctrl, j, e, phi))

        def piece(c, H, size):
            gen = jnp.concatenate([rh * (E @ P @ H), jnp.zeros((n, 1))], axis=1)
            err = affine.symbols(rh * (E @ P @ c), gen)
            # e^{A t} = e^{A t_c} e^{A (t - t_c)}: the second factor's distance from I, an error term
            slack = jnp.linalg.norm(E, axis=1) * g * rh * size * (1 + 1e-12) + 1e-15 * rh
            err = affine.Affine(err.c, err.g, err.e + slack)
            out, ctx = affine.enclose(fn, jet, err, n_ball=n if ball else 0)
            box = affine.to_interval(out, ctx)
            ok = (box.lo >= -limit) & (box.hi <= limit) & jnp.isfinite(box.lo) & jnp.isfinite(box.hi)
            return jnp.all(ok)

        return jnp.all(jax.vmap(piece)(*cover))

    return (jax.vmap(one)(affine.Affine(jc, jg, je), t_c, growth, rho),)


def _box_radii(
    ctrl, turn: bool, params, P, limit, breaks, t_c, h, *, rho_hi: float, iters: int, cover: Cover, rho_lo=None
):
    """Bisection per box on rho in [rho_lo, rho_hi] (``rho_lo``, known to fit, default 0): the
    largest rho whose box fits over every piece of ``cover`` (``rho_lo`` if none above it). A box
    that fits at ``rho_hi`` is done in one test; only the others are bisected (a box's result does
    not depend on the boxes evaluated beside it). ``breaks``: the reference's, as :func:`time_boxes`
    gives them (the boxes' jets are their pieces')."""
    jets = box_jets(ctrl, params, breaks, t_c, h)
    pieces = tuple(jnp.asarray(x) for x in cover[:3])
    program = lambda *a: _box_fits(ctrl, turn, cover.ball, params, P, limit, pieces, *a)
    block = BOX_BLOCK if cover.ball else PIECE_BLOCK
    fits = lambda i, rho: np.asarray(fixed_blocks(program, (*(x[i] for x in jets), t_c[i], h[i], rho), block)[0], bool)
    lo = np.zeros_like(t_c) if rho_lo is None else np.asarray(rho_lo, float).copy()
    top = fits(np.arange(t_c.size), np.full_like(t_c, rho_hi))
    rest = np.flatnonzero(~top)
    lo_r, hi_r = lo[rest], np.full(rest.size, rho_hi)
    for _ in range(iters if rest.size else 0):
        mid = 0.5 * (lo_r + hi_r)
        ok = fits(rest, mid)
        lo_r, hi_r = np.where(ok, mid, lo_r), np.where(ok, hi_r, mid)
    lo[rest] = lo_r
    return np.where(top, rho_hi, lo)


def command_at(ctrl, params, t, initial_error):
    """The nominal loop's command at time ``t`` [s] from the initial output error
    ``initial_error`` ((n,)): :func:`command` at the reference's jet and :math:`e^{At}` times it."""
    jet = ctrl.reference_jet(t, params)[: ctrl.relative_degree + 1]
    return command(ctrl, params, jet, _math.expm_small(ctrl.error_matrix(params.gains) * t) @ initial_error)


@functools.partial(jax.jit, static_argnums=0)
def _ray_commands(ctrl, params, P, ts, dirs, radii):
    """Commands at (time, direction, radius): shape (T, D, R, n_input)."""
    at = lambda t, d, rho: command_at(ctrl, params, t, P @ (rho * d))
    f = jax.vmap(jax.vmap(jax.vmap(at, (None, None, 0)), (None, 0, None)), (0, None, None))
    return f(ts, dirs, radii)


def _check_periodic(ctrl, params, t_final: float) -> None:
    """The command must not change when an angle output of the reference turns by 2 pi (the
    reference's jet is enclosed modulo 2 pi): checked at a few times, else ValueError."""
    angles = tuple(ctrl.law.extension.angle_outputs)
    if not angles:
        return
    r, n = ctrl.relative_degree, ctrl.relative_degree * ctrl.m
    for t in np.linspace(0.0, t_final, 5):
        jet = ctrl.reference_jet(t, params)[: r + 1]
        turned = jet.at[0, jnp.asarray(angles)].add(2 * np.pi)
        a, b = (np.asarray(command(ctrl, params, j, jnp.zeros(n))) for j in (jet, turned))
        if not np.allclose(a, b, rtol=1e-9, atol=1e-9):
            raise ValueError(
                f"the {ctrl.robot.name} law's command changes when its reference heading turns by 2 pi "
                f"({a.tolist()} vs {b.tolist()} at t = {t:g} s): the saturation-free radius encloses "
                "the reference's angles modulo 2 pi and cannot bound it"
            )


RAY_RADII = 151
"""Radii per ray of the attained bound, from the proved radius to 4 times it."""
RAY_TIMES = 16
"""Times at which the rays are tried: t = 0 and the worst boxes' centres (:func:`_worst_times`)."""


def compile_programs(ctrl, turn: bool, params, n_directions: int, covers=(), pinned: bool = False) -> None:
    """Compile the programs of :func:`saturation_free_radius` at once, each on a thread of its own
    (XLA compiles them in parallel; the search then finds them compiled): the reference's boxes
    (``pinned``: each to its piece, :func:`jet_boxes`), the fit over the whole ball and over each
    of ``covers`` (:class:`Cover`), and the rays."""
    n, f = ctrl.relative_degree * ctrl.m, jnp.float64
    P, lim = jnp.zeros((n, n), f), jnp.zeros(ctrl.robot.n_input, f)
    piece = lambda block: jnp.zeros(block, jnp.result_type(int)) if pinned else None

    def fit_job(cover: Cover, block: int):
        blk = jnp.zeros(block, f)
        jets = jax.eval_shape(lambda tc, hh: jet_boxes(ctrl, params, tc, hh, piece(block)), blk, blk)
        jets = [jnp.zeros(x.shape, x.dtype) for x in jets]
        pieces = tuple(jnp.asarray(x) for x in cover[:3])
        return lambda: _box_fits.lower(ctrl, turn, cover.ball, params, P, lim, pieces, *jets, blk, blk, blk).compile()

    blk = jnp.zeros(BOX_BLOCK, f)
    jobs = [
        lambda: jet_boxes.lower(ctrl, params, blk, blk, piece(BOX_BLOCK)).compile(),
        fit_job(whole_ball(n), BOX_BLOCK),
        *[fit_job(c, PIECE_BLOCK) for c in covers],
        lambda: _ray_commands.lower(
            ctrl, params, P, jnp.zeros(RAY_TIMES, f), jnp.zeros((n_directions, n), f), jnp.zeros(RAY_RADII, f)
        ).compile(),
    ]
    with concurrent.futures.ThreadPoolExecutor(len(jobs)) as pool:
        for fut in [pool.submit(j) for j in jobs]:
            fut.result()


def _attained(ctrl, params, P, limit, ts, rho_lo: float, rho_hi: float, n_dirs: int, seed: int):
    """Smallest radius on a grid of rays (at the given times) whose command exceeds a limit: on
    ``[rho_lo, 4 rho_lo]``, then, where none does there, on a geometric grid up to ``rho_hi`` (a
    proof far below the attained radius: the car's full slice, 0.029 where no ray saturated
    below 0.12)."""
    k = P.shape[1]
    d = np.random.default_rng(seed).normal(size=(n_dirs, k))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.concatenate([d, np.zeros((n_dirs, P.shape[0] - k))], axis=1)  # on the padded basis
    P = _padded(P)
    grids = [rho_lo * np.linspace(1.0, 4.0, RAY_RADII)]
    if rho_hi > 4.0 * rho_lo:
        grids.append(np.geomspace(4.0 * rho_lo, rho_hi, RAY_RADII + 1)[1:])
    for radii in grids:  # one compiled program: RAY_RADII radii each
        u = np.asarray(_ray_commands(ctrl, params, P, jnp.asarray(ts), jnp.asarray(d), jnp.asarray(radii)))
        over = np.any(np.abs(u) > np.asarray(limit), axis=-1) | ~np.all(np.isfinite(u), axis=-1)
        if over.any():
            it, id_, ir = np.unravel_index(np.argmin(np.where(over, radii[None, None, :], np.inf)), over.shape)
            return float(radii[ir]), np.asarray(P) @ (radii[ir] * d[id_]), float(ts[it])
    return np.inf, None, None


PIECE_ROUNDS = 24
"""Rounds of :func:`_pieced` at most, each over the :data:`PIECE_BLOCK` boxes with the smallest radii."""
PIECE_ITERS = 16
"""Bisection steps over the pieces for a box that fails its first test (between its proved
radius and half of :data:`PIECE_GAP` under the attained one)."""
PIECE_GAP = 0.02
""":func:`_pieced` stops once the proved radius is within this fraction of the attained one."""


def _pieced(radii, attain, cover: Cover, t_c, h, rho, rho_hi: float, best):
    """The boxes that limit the radius bounded again over ``cover``'s pieces, the smallest first:
    each round takes the :data:`PIECE_BLOCK` smallest below the target, :data:`PIECE_GAP` under
    the smallest attained bound ``best`` ``(radius, error, time)``. One not yet pieced is bounded
    over the pieces, one already pieced is halved in time and its halves bounded over them, each
    tested first at half the gap under ``best`` and bisected below it only if it fails there. A box's radius
    starts from the one proved for it or for the box it was cut from (each bisection step is a
    proof of its own), so it never falls. After each round ``attain(times, rho)`` (the attained
    bound at the smallest boxes' times, :func:`_attained`) may lower ``best``; the rounds stop
    once every box reaches the target. Returns the boxes' centres, half-widths and radii, and the
    smallest attained bound (rays tried at the final boxes: by the last round or, with none, by
    the caller)."""
    pieced = np.zeros(rho.size, bool)
    for _ in range(PIECE_ROUNDS):
        target = min(rho_hi, (1.0 - PIECE_GAP) * best[0])
        aim = min(rho_hi, (1.0 - 0.5 * PIECE_GAP) * best[0])  # above the target: one test usually lands it there
        if rho.min() >= target:
            break
        order = np.argsort(rho, kind="stable")[:PIECE_BLOCK]
        sel = np.zeros(rho.size, bool)
        sel[order[rho[order] < target]] = True
        fresh, split = sel & ~pieced, sel & pieced
        tc = np.concatenate([t_c[fresh], t_c[split] - 0.5 * h[split], t_c[split] + 0.5 * h[split]])
        hh = np.concatenate([h[fresh], np.tile(0.5 * h[split], 2)])
        lo = np.concatenate([rho[fresh], np.tile(rho[split], 2)])
        new = radii(tc, hh, cover=cover, rho_lo=lo, rho_hi=aim, iters=PIECE_ITERS)
        t_c, h, rho = (np.concatenate([x[~sel], y]) for x, y in ((t_c, tc), (h, hh), (rho, new)))
        pieced = np.concatenate([pieced[~sel], np.ones(tc.size, bool)])
        best = min(best, attain(_worst_times(t_c, rho), rho.min()), key=lambda x: x[0])
    return t_c, h, rho, best


def _worst_times(t_c, rho):
    """The times of the attained bound's rays: t = 0 (where the initial error is whole; on
    ``steered_21``'s position slice the limit binds there first) and the centres of the
    :data:`RAY_TIMES` - 1 boxes with the smallest radii."""
    return np.concatenate([[0.0], t_c[np.argsort(rho, kind="stable")[: RAY_TIMES - 1]]])


def saturation_free_radius(
    ctrl,
    params,
    input_limit,
    *,
    t_final: float,
    basis=Slice.FULL,
    n_boxes: int = 512,
    rounds: int = 4,
    rho_max: float = 10.0,
    iters: int = 24,
    n_directions: int = 64,
    seed: int = 0,
    pieces: bool = True,
) -> SaturationFreeRadius:
    """Proved lower and attained upper bounds of the saturation-free radius (module docstring).

    Args:
      ctrl: a dynamic linearizing controller with constant gains.
      params: its parameters.
      input_limit: (n_input,) limits on the plant's inputs (velocity level: [m/s, rad/s] as the
        plant's inputs; torque level: on their rates), > 0 (inf: none).
      t_final: horizon T [s].
      basis: the slice (``"full"``, ``"position"`` or an (n, k) basis).
      n_boxes: time boxes at first.
      rounds: times the worst eighth of the boxes is halved.
      rho_max: largest radius tried.
      iters: bisection steps per box.
      n_directions: rays for the attained bound.
      seed: their seed.
      pieces: on a 2-dimensional slice (the position slice), bound the boxes that limit the
        radius again over :func:`disc_cover`'s pieces (False: over the whole disc only).

    Raises:
      ValueError: a static law, a gain schedule, limits of the wrong shape or not > 0.
    """
    check_dynamic(ctrl)
    if params.gains.time_varying:
        raise ValueError("the saturation-free radius needs constant gains (the error is e^{At} s)")
    nu = ctrl.robot.n_input
    limit = np.asarray(input_limit, float)
    if limit.ndim > 1 or (limit.ndim == 1 and limit.shape[0] != nu):
        raise ValueError(f"input_limit must be a scalar or have {nu} entries (one per input), got shape {limit.shape}")
    limit = np.broadcast_to(limit, (nu,))
    if np.any(~(limit > 0)):
        raise ValueError(f"input_limit must be > 0 per input (inf: none), got {limit.tolist()}")
    if not np.any(np.isfinite(limit)):  # no limit at all: nothing can saturate
        return SaturationFreeRadius(np.inf, np.inf, None, None, 0)
    P = slice_basis(ctrl, basis)
    Pn, n = _padded(P), P.shape[0]
    _check_periodic(ctrl, params, t_final)
    turn = turns_alike(ctrl, params, t_final)
    cover = disc_cover(n) if pieces and P.shape[1] == 2 else None
    t_c, h, breaks = time_boxes(params.reference, t_final, n_boxes)
    compile_programs(ctrl, turn, params, n_directions, () if cover is None else (cover,), pinned=breaks is not None)
    lim = jnp.asarray(np.where(np.isfinite(limit), limit, np.finfo(float).max))
    radii = functools.partial(_box_radii, ctrl, turn, params, Pn, lim, breaks, iters=iters)
    rho = radii(t_c, h, cover=whole_ball(n), rho_hi=rho_max)
    for _ in range(rounds):
        worst = rho <= np.quantile(rho, 0.125)
        tc2 = np.concatenate([t_c[worst] - 0.5 * h[worst], t_c[worst] + 0.5 * h[worst]])
        h2 = np.tile(0.5 * h[worst], 2)
        rho2 = radii(tc2, h2, cover=whole_ball(n), rho_hi=rho_max)
        t_c, h, rho = (
            np.concatenate([t_c[~worst], tc2]),
            np.concatenate([h[~worst], h2]),
            np.concatenate([rho[~worst], rho2]),
        )
    attain = lambda ts, lo: _attained(ctrl, params, P, lim, ts, max(lo, 1e-9), rho_max, n_directions, seed)
    up, err, t_up = attain(_worst_times(t_c, rho), float(rho.min()))
    if cover is not None:
        t_c, _, rho, (up, err, t_up) = _pieced(radii, attain, cover, t_c, h, rho, rho_max, (up, err, t_up))
    return SaturationFreeRadius(float(rho.min()), up, err, t_up, int(t_c.size))


def limit_usage(ctrl, params, limit, direction, t, rho):
    r"""The largest fraction of its limit that the nominal loop's command uses at time ``t`` from
    the initial error ``rho * direction``: :math:`\max_i |u_i(t, \rho d)| / \bar u_i` (1 on the
    saturation-free radius's boundary). Traceable in the gains, ``t`` and ``rho`` (a gradient for
    :func:`saturation_free_sensitivity`).

    Args:
      ctrl: a dynamic linearizing controller with constant gains.
      params: its parameters.
      limit: (n_input,) the limits, > 0 (a large finite value for none).
      direction: (n,) the initial output error's direction (unit in the slice's coordinates).
      t: time [s].
      rho: the radius [output-error units].
    """
    return jnp.max(jnp.abs(command_at(ctrl, params, t, rho * direction)) / limit)


def saturation_free_sensitivity(usage_grad, sat: SaturationFreeRadius, theta):
    r"""The saturation-free radius's derivative in the parameters ``theta`` of the gains, by the
    implicit function theorem at its attained point (``sat.worst_error`` at ``sat.worst_time``,
    where the command meets its limit, :math:`g(\theta, \rho) = 1` for :func:`limit_usage`):
    :math:`\partial\rho/\partial\theta = -g_\theta / g_\rho`, scaled by ``lower_bound /
    upper_bound`` (the proved bound's ratio to the attained one). It is the attained bound's
    derivative (the envelope theorem at its minimising time and direction, which the rays
    approximate), a direction for a step, not a bound; zero where no point was attained.

    Args:
      usage_grad: ``(theta, direction, t, rho) -> (g_theta, g_rho)``, the gradient of
        :func:`limit_usage` with the gains a function of ``theta``.
      sat: :class:`SaturationFreeRadius` at ``theta``.
      theta: the parameters (an array).
    """
    theta = jnp.asarray(theta)
    if sat.worst_error is None or not np.isfinite(sat.upper_bound) or sat.upper_bound <= 0:
        return jnp.zeros_like(theta)
    direction = jnp.asarray(sat.worst_error) / sat.upper_bound
    g_theta, g_rho = usage_grad(theta, direction, sat.worst_time, sat.upper_bound)
    if not np.isfinite(float(g_rho)) or float(g_rho) <= 0.0:
        return jnp.zeros_like(theta)
    return -g_theta / g_rho * (sat.lower_bound / sat.upper_bound)
