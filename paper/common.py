"""What the paper's reproductions share: the §6.1 set-up, and the command line and figure of the
two tracking experiments (not installed: run from the repository, ``python -m paper.NAME``)."""

from __future__ import annotations

import sys
import time

import jax.numpy as jnp
import numpy as np

import wmrjax as w
from wmrjax import Level, references
from wmrjax._files import headless_pyplot as pyplot
from wmrjax._files import write_json, write_npz
from wmrjax._files import write_png as save_figure
from wmrjax._math import quantiles
from wmrjax.cli import machine, options, running
from wmrjax.cli.machine import enable_x64

__all__ = [
    "enable_x64",
    "pyplot",
    "quantiles",
    "save_figure",
    "section_6_1_setup",
    "tracking_cli",
    "tracking_figure",
    "write_json",
    "write_npz",
]


def section_6_1_setup():
    """The paper's §6.1 closed loop: (2,0), e = 0, reference (62), poles -1, initial condition (63).

    Returns:
      ``(ctrl, params, z0, zeta0)``.
    """
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(references.paper_62(), poles=1.0, geometry=w.Geometry(e=0.0))
    p0 = params.reference.position(jnp.asarray(0.0))
    v0 = params.reference.velocity(jnp.asarray(0.0))
    # (63): x(0) = x_ref(0) - 0.54, y(0) = y_ref(0) + 0.54, velocities equal to the reference's
    zeta0 = jnp.array([[p0[0] - 0.54, p0[1] + 0.54], [v0[0], v0[1]]])
    z0 = ctrl.initial_state(zeta0, params)
    return ctrl, params, z0, zeta0


# --- the tracking experiments (posture_tracking, static_tracking) ------------------------------


def tracking_cli(argv, doc, default_out, kinds, run_fn) -> int:
    """The command line shared by the tracking experiments."""
    p = options.parser(doc.splitlines()[0], default_out)
    p.add_argument("--n-random", type=options.count, default=1024, help="random references per (type, level)")
    p.add_argument("--t-final", type=options.positive, default=15.0, help="horizon [s]")
    p.add_argument("--dt", type=options.positive, default=0.01, help="RK4 step [s]")
    p.add_argument("--seed", type=options.seed, default=0, help="PRNG seed of the random references and initial errors")
    p.add_argument("--types", nargs="+", default=list(kinds), help=f"subset of {' '.join(kinds)}")
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    machine.check_horizon(p, t_final=a.t_final, dt=a.dt, batch=a.n_random, n_state=7, saved_every=10)
    try:
        chosen = tuple(w.robot_type(k).name for k in a.types)
    except ValueError as exc:
        p.error(f"argument --types: {exc}")
    bad = [k for k in chosen if k not in kinds]
    if bad:
        p.error(f"argument --types: {bad} not among this experiment's types {list(kinds)}")
    t0 = time.perf_counter()
    running.work(
        p, a, lambda progress: run_fn(a.out, a.n_random, a.t_final, a.dt, a.seed, kinds=chosen, progress=progress)
    )
    print(f"wrote {a.out}/summary.json and one PNG per type ({time.perf_counter() - t0:.0f} s)", file=sys.stdout)
    return 0


def tracking_figure(out_dir, kind, per_level, prefix="posture", error_label="position error |(x, y) - (x, y)_ref| [m]"):
    """Paths of the circle and figure-eight runs at both levels, errors vs time, histogram of
    final errors over the random batch: ``{prefix}_{type}.png``. ``per_level[level]`` is
    ``(traces, (final_errors, ...))`` with traces[name] holding t, state (its first two
    columns are the tracked point), ref, ep."""
    plt = pyplot()
    fig, axs = plt.subplots(2, 2, figsize=(10, 8.5))
    for j, name in enumerate(list(next(iter(per_level.values()))[0])[:2]):  # the two named runs
        ax = axs[0, j]
        tr0 = next(iter(per_level.values()))[0][name]
        ax.plot(tr0["ref"][:, 0], tr0["ref"][:, 1], "k--", lw=1.2, label="reference")
        for lvl, c in zip(Level, ("C0", "C3")):
            if lvl not in per_level:
                continue
            st = per_level[lvl][0][name]["state"]
            ax.plot(st[:, 0], st[:, 1], c, lw=1.2, label=f"robot, {lvl} level")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(f"type {kind}: {name.replace('_', '-')}")
        ax.axis("equal")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    ax_t, ax_h = axs[1, 0], axs[1, 1]
    for lvl, c in zip(Level, ("C0", "C3")):
        if lvl not in per_level:
            continue
        traces, (ep_random, _) = per_level[lvl]
        for name, ls in zip(list(traces)[:2], ("-", ":")):
            tr = traces[name]
            ax_t.semilogy(tr["t"], np.maximum(tr["ep"], 1e-12), c + ls, label=f"{name.replace('_', '-')}, {lvl}")
        if ep_random.size:
            ax_h.hist(np.log10(np.maximum(ep_random, 1e-16)), bins=40, color=c, alpha=0.6, label=f"{lvl} level")
    ax_t.set_xlabel("t [s]")
    ax_t.set_ylabel(error_label)
    ax_h.set_xlabel("log10 final position error [m] (random references)")
    ax_h.set_ylabel("runs")
    for ax in (ax_t, ax_h):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out_dir / f"{prefix}_{kind.strip('()').replace(',', '')}.png")
    plt.close(fig)
