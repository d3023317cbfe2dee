"""The field's state-independent part computed before the loop (wmrjax._hoist): the cut
reproduces the field, a sampled path leaves the loop what a built-in reference leaves it, and
the runs where the table would be batched or too large keep the whole field in the loop."""

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import _hoist
from wmrjax import references as R

simulate_module = importlib.import_module("wmrjax.simulate")

TIMES = np.array([0.0, 2.5, 6.0, 10.0])


def _sampled(params, rate_hz=20.0, horizon=10.0):
    """``params`` with the §6.1 reference replaced by its samples at ``rate_hz`` (a quintic spline)."""
    ts = np.linspace(0.0, horizon, int(round(horizon * rate_hz)) + 1)
    xy = np.asarray(jax.vmap(params.reference.position)(jnp.asarray(ts)))
    return params._replace(reference=R.from_samples(ts, xy))


def _scheduled_11():
    """(1,1) at torque level on the figure-eight, with strongly varying scheduled gains."""
    ctrl = w.dynamic_linearization("(1,1)", "torque")
    om = np.array([1.0, 2.2, 1.4, 1.8])[:, None, None] * np.array([1.0, 1.3])  # (K, m, r / 2)
    ze = np.array([1.0, 0.6, 0.8, 0.7])[:, None, None] * np.ones((4, 2, 2))
    gains = w.GainSchedule.from_damping(TIMES, om * np.ones((4, 2, 2)), ze)
    ref = R.figure_eight(heading_offset=ctrl.row.default_heading_offset)
    params = ctrl.params(ref, geometry=ctrl.row.default_geometry, gains=gains)
    z0 = ctrl.reference_state(0.0, params).at[0].add(0.05)
    return ctrl, params, z0


def _split(ctrl, params, z0):
    field_s, closed, out_tree = simulate_module._scalar_field(ctrl, jnp.zeros(()), z0, params)
    n_params = len(jax.tree_util.tree_leaves(params))
    return field_s, _hoist.split_field(closed, out_tree, len(jax.tree_util.tree_leaves(z0)), [False] * n_params)


@pytest.mark.parametrize("case", ["sampled_61", "scheduled_11"])
def test_the_cut_field_is_the_field(case, paper61, rng):
    """Evaluated op by op (no compiler in between), the three programs of the cut give the whole
    field's numbers to the last bit, at stage times and states off the reference."""
    if case == "sampled_61":
        ctrl, params, z0 = paper61
        params = _sampled(params)
    else:
        ctrl, params, z0 = _scheduled_11()
    field_s, split = _split(ctrl, params, z0)
    assert split.n_timed > 0 and split.n_consts > 0
    consts, inputs = _hoist.constants(split, jax.tree_util.tree_leaves(params))
    times = _hoist.stage_times(jnp.asarray(0.3), jnp.asarray(0.01), 5)
    table = _hoist.tabulate(split, inputs, times)
    for i in range(5):
        for s in range(_hoist.STAGE_TIMES):
            z = z0 + 0.05 * jnp.asarray(rng.standard_normal(z0.shape))
            whole = field_s(times[i, s], z, params)
            cut = _hoist.field_at(split, consts, tuple(r[i] for r in table[s]), z)
            for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(cut)):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _loop_equations(jaxpr, n_steps: int, inside: bool = False) -> int:
    """Equations inside the time loop of a traced run: those of its scans over ``n_steps`` steps,
    nested programs included."""
    count = 0
    for eqn in jaxpr.eqns:
        count += inside
        loop = inside or (eqn.primitive.name == "scan" and eqn.params["length"] == n_steps)
        count += sum(_loop_equations(sub, n_steps, loop) for sub in jax.extend.core.jaxprs_in_params(eqn.params))
    return count


@pytest.mark.parametrize("level", ["velocity", "torque"])
def test_a_sampled_path_leaves_the_loop_what_a_builtin_reference_leaves(level):
    """The reference's jet is evaluated before the loop: the §6.1 time loop of a batch has as many
    equations with the path sampled at 20 Hz (a spline: piece search, Horner's rule) as with its
    closed form (62). Before the jets were tabulated the sampled loop held 2.2x the equations at
    velocity level (the field's 320 against 146)."""
    ctrl = w.dynamic_linearization("(2,0)", level)
    params = ctrl.params(R.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))
    z0s = jnp.stack([ctrl.reference_state(0.0, params)] * 2)
    counts = {}
    for name, p in (("builtin", params), ("sampled", _sampled(params))):
        run = jax.vmap(lambda z, p=p: w.simulate(ctrl, z, p, dt=0.01, n_steps=100, save_every=100))
        counts[name] = _loop_equations(jax.make_jaxpr(run)(z0s).jaxpr, 100)
    assert counts["sampled"] == counts["builtin"] > 0, counts


def test_what_depends_on_batched_parameters_stays_in_the_loop(paper61, monkeypatch):
    """A table is built only from what the runs of a batch share. References that differ per run
    (vmap over their parameters) keep their jet in the loop (a table of it would be batch x steps
    x values); gains that differ per run on a shared reference keep the reference's jet
    tabulated. Either batch equals each run on its own (everything shared: tabulated) to rounding."""
    ctrl, params, _ = paper61
    seen = []
    original = _hoist.split_field

    def spy(closed, out_tree, n_state, varying):
        split = original(closed, out_tree, n_state, varying)
        seen.append((sum(varying), split.n_timed))
        return split

    monkeypatch.setattr(_hoist, "split_field", spy)
    run = lambda z, p: w.simulate(ctrl, z, p, dt=0.01, n_steps=300)
    refs = [R.circle(radius=r, omega=0.5) for r in (2.0, 3.0)]
    per_run = [
        params._replace(reference=refs[0], gains=w.Gains.from_poles(1.0, 2, 2)),
        params._replace(reference=refs[1]),
    ]
    per_run.append(params._replace(reference=refs[0], gains=w.Gains.from_poles(2.0, 2, 2)))
    z0s = jnp.stack([ctrl.reference_state(0.0, p).at[0].add(0.1) for p in per_run])
    stack = lambda ps: jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ps)
    alone = [run(z, p) for z, p in zip(z0s, per_run)]
    n_alone = seen[0][1]
    seen.clear()
    refs_batched = jax.vmap(run)(z0s[:2], stack(per_run[:2]))  # references (and gains) per run
    gains = params.gains._replace(coeffs=jnp.stack([per_run[0].gains.coeffs, per_run[2].gains.coeffs]))
    pair = z0s[jnp.array([0, 2])]
    jax.vmap(run, in_axes=(0, None))(pair, per_run[0])  # everything shared
    gains_batched = jax.vmap(lambda z, g: run(z, per_run[0]._replace(gains=g)))(pair, gains)
    (v_refs, t_refs), (v_shared, t_shared), (v_gains, t_gains) = seen
    assert n_alone > 0 and t_shared == t_gains == n_alone  # the reference's jet tabulated
    assert v_shared == 0 and 0 < v_gains < v_refs  # gains batched: fewer varying leaves
    assert t_refs < n_alone  # the references' jets stay in the loop
    for k in (0, 1):
        np.testing.assert_allclose(refs_batched.state[k], alone[k].state, rtol=0, atol=1e-12)
    for k, j in ((0, 0), (1, 2)):
        np.testing.assert_allclose(gains_batched.state[k], alone[j].state, rtol=0, atol=1e-12)


def test_batched_sees_through_vmap_jvp_and_jit():
    """:func:`wmrjax._hoist.batched` answers at trace time: a vmapped argument is batched, an
    ``in_axes=None`` one is not, through a jvp inside the vmap too; inside a jit it sees nothing."""
    seen = {}

    def probe(name):
        def f(x, y):
            seen[name] = (_hoist.batched(x), _hoist.batched(y))
            return x + y

        return f

    x, y = jnp.arange(3.0), jnp.asarray(1.0)
    jax.vmap(probe("vmap"), in_axes=(0, None))(x, y)
    jax.vmap(lambda a, b: jax.jvp(probe("jvp"), (a, b), (a, b))[0], in_axes=(0, None))(x, y)
    jax.jit(probe("jit"))(x, y)
    assert seen == {"vmap": (True, False), "jvp": (True, False), "jit": (False, False)}


def test_tabulated_schedule_agrees_with_the_whole_field_and_its_gradients_agree(paper61, monkeypatch):
    """A gain schedule's coefficients are tabulated with the reference's jet (§6.1 loop, scheduled
    gains): the run equals the whole field in the loop (a table over its byte limit) to rounding,
    and the gradient through the table equals in forward and reverse mode and against central
    differences."""
    ctrl, params, z0 = paper61
    om = np.array([1.0, 2.2, 1.4, 1.8])[:, None, None] * np.ones((4, 2, 1))
    ze = np.array([1.0, 0.6, 0.8, 0.7])[:, None, None] * np.ones((4, 2, 1))
    params = params._replace(gains=w.GainSchedule.from_damping(TIMES, om, ze))
    n = 300
    tab = w.simulate(ctrl, z0, params, dt=0.01, n_steps=n)
    monkeypatch.setattr(_hoist, "TABLE_MAX_BYTES", 0)
    whole = w.simulate(ctrl, z0, params, dt=0.01, n_steps=n)
    monkeypatch.undo()
    assert not bool(tab.diagnostics.failed)
    np.testing.assert_allclose(tab.state, whole.state, rtol=0, atol=1e-12)

    def loss(scale):
        g = params.gains._replace(omega=params.gains.omega * scale)
        tr = w.simulate(ctrl, z0, params._replace(gains=g), dt=0.01, n_steps=n, save_every=n)
        return jnp.sum(tr.final_state[:2] ** 2)

    s = jnp.asarray(1.1)
    fwd = jax.jacfwd(loss)(s)
    rev = jax.grad(loss)(s)
    h = 1e-5
    fd = (loss(s + h) - loss(s - h)) / (2 * h)
    np.testing.assert_allclose(fwd, rev, rtol=1e-10)
    np.testing.assert_allclose(rev, fd, rtol=1e-6)


def test_rewrites_off_runs_the_whole_field_in_the_loop(paper61, monkeypatch):
    """``WMRJAX_JAXPR_REWRITES=0`` (the plain JAX program, to rule the rewriters out) also turns
    the tabulation off; the run agrees with the tabulated one to rounding."""
    ctrl, params, z0 = paper61
    params = _sampled(params)
    calls = []
    original = simulate_module._hoisting
    monkeypatch.setattr(simulate_module, "_hoisting", lambda *a: calls.append(1) or original(*a))
    tab = w.simulate(ctrl, z0, params, dt=0.01, n_steps=200)
    monkeypatch.setenv("WMRJAX_JAXPR_REWRITES", "0")
    plain = w.simulate(ctrl, z0, params, dt=0.01, n_steps=200)
    assert calls == [1]
    np.testing.assert_allclose(tab.state, plain.state, rtol=0, atol=1e-12)
