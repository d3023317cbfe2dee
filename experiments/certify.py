r"""Lemma 2 certification of any restricted type along any named reference.

    python -m experiments.certify --robot "(2,0)" --reference paper_62 --out results/certify_20

For the dynamic linearizing law (velocity level by default) this computes, over the horizon:
the certified radii of Lemma 2 with K2 three ways (the paper's eq 64 when the gains are the
paper's, the automatic Lyapunov bound, the exact ||e^{At}||); the exact-map radius (the
largest ball of initial errors that keeps zeta(t) eps away from the singular set, from
zeta_err(t) = e^{At} zeta_err(0)) for the full error and for the position slice; an
empirical check by batch simulation (violations of (53) and singular runs inside every
ball, and the empirical safe radius per direction of the position slice); and the
gradient falsifier's smallest failing radius, full and position slice.

Writes ``summary.json`` and ``slice_map.png``: min_t dist(zeta(t), S) over a grid of
initial position errors (velocities equal to the reference's), with the eps contour and
every certified circle.

For (1,2) the singular set is curved (sigma(zeta) = 0, see wmrjax.certify.m1_closed_form): M1
is a one-dimensional minimisation, and the exact-map radius comes from a branch and bound
with a proved lower bound (``radius_exact_map_lower_bound``, ``radius_exact_map_gap``).
Every certificate's ratio to the falsified radius is in ``tightness``; ``wall_time_s`` is the
whole run. The batch simulations are spread over one JAX host device per core (``--devices``).
"""

from __future__ import annotations

import os
import sys
import time

from experiments import common


def setup(robot, reference, level="velocity", poles=1.0, heading_offset=None, geometry=None):
    """The closed loop to certify: ``geometry`` (L, e, delta) if given, else the paper's geometry
    along the paper's references (62) and (66) where the paper has one (§6: (2,0), e = 0), else
    the type's default geometry (its Table 4 row); the row's default heading offset unless
    ``heading_offset`` is given."""
    import wmrjax as w
    from wmrjax import references as R

    ctrl = w.dynamic_linearization(robot, level)
    ref = R.named(reference)
    off = ctrl.row.default_heading_offset if heading_offset is None else heading_offset
    if off:
        ref = ref.with_heading_offset(off)
    if geometry is not None:
        g = w.Geometry(*geometry)
    elif reference in ("paper_62", "paper_66") and ctrl.row.paper_geometry is not None:
        g = ctrl.row.paper_geometry
    else:
        g = ctrl.row.default_geometry
    return ctrl, ctrl.params(ref, poles=poles, geometry=g)


def slice_map(ctrl, params, block, path, *, t_final, dt, eps, n_grid=81, title=""):
    """PNG: log10 min_t dist over a grid of initial position errors, eps contour, certified circles."""
    import jax.numpy as jnp
    import numpy as np

    from wmrjax import certify as C

    R = 1.25 * max(v for k, v in block.items() if k.startswith("radius_") and v is not None)
    xs = np.linspace(-R, R, n_grid)
    X, Y = np.meshgrid(xs, xs)
    P = np.asarray(C.slice_basis(ctrl, "position"))
    errs = np.stack([X.ravel(), Y.ravel()], 1) @ P.T
    d, s = C.min_distance(ctrl, params, t_final=t_final, initial_errors=jnp.asarray(errs), dt=dt)
    d = np.where(np.asarray(s), 0.0, np.asarray(d)).reshape(X.shape)
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    im = ax.pcolormesh(X, Y, np.log10(np.maximum(d, 1e-6)), cmap="viridis", shading="auto")
    fig.colorbar(im, ax=ax, label="log10 min_t dist(zeta(t), singular set)" if C.singular_rows(ctrl) else
                 "log10 min_t dist(zeta(t), singular set) (capped at 1)")
    bad = d < eps
    if bad.any():
        ax.plot(X[bad], Y[bad], "rs", ms=2.5, label=f"unsafe: comes within eps = {eps}")
    th = np.linspace(0, 2 * np.pi, 200)
    for i, (k, lab) in enumerate([("radius_paper", "Lemma 2, K2 of (64)"), ("radius_lyapunov", "Lemma 2, Lyapunov K2"),
                                  ("radius_exact_norm", "Lemma 2, K2 = ||exp(At)||"),
                                  ("radius_exact_map_position_slice", "exact map (position slice)"),
                                  ("empirical_radius_position_slice", "empirical (position slice)")]):
        r = block.get(k)
        if r is not None:
            ax.plot(r * np.cos(th), r * np.sin(th), color=f"C{i + 1}", lw=1.4, ls="--" if "empirical" in k else "-",
                    label=f"{lab}: {r:.3g}")
    ax.set_xlabel("initial error in x_P [m]")
    ax.set_ylabel("initial error in y_P [m]")
    ax.set_title(title or "initial position errors (velocities = reference's)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper right")
    common.save_figure(fig, path)
    plt.close(fig)
    return {"n_grid": n_grid, "half_width": R, "fraction_unsafe": float(bad.mean())}


def run(out, robot="(2,0)", reference="paper_62", level="velocity", poles=1.0, t_final=10.0, eps=1e-2, dt=0.01,
        n_empirical=4096, n_directions=128, n_starts=16, heading_offset=None, map_grid=81, seed=0,
        geometry=None, progress=None) -> dict:
    say = progress or (lambda msg: print(msg, flush=True))
    common.enable_x64()
    t0 = time.time()
    ctrl, params = setup(robot, reference, level, poles, heading_offset, geometry)
    say(f"certify {ctrl.robot.name} ({level}) along {reference}, T = {t_final} s, eps = {eps}")
    from wmrjax import certify as C

    report = C.analyse(ctrl, params, t_final=t_final, eps=eps, dt=dt, n_empirical=n_empirical,
                       n_directions=n_directions, n_starts=n_starts, seed=seed, log=say)
    say(f"slice map ({map_grid} x {map_grid} runs)")
    block = report.summary()
    out.mkdir(parents=True, exist_ok=True)
    summary = {"experiment": "certify", "robot": ctrl.robot.name, "level": level, "reference": reference,
               "heading_offset": float(params.reference.heading_offset), "geometry": params.geometry._asdict(),
               "poles": poles, "dt": dt, **block}
    summary["slice_map"] = slice_map(ctrl, params, block, out / "slice_map.png", t_final=t_final, dt=dt, eps=eps,
                                     n_grid=map_grid, title=f"{ctrl.robot.name} along {reference}: initial position errors")
    summary["wall_time_s"] = time.time() - t0
    common.write_json(out / "summary.json", summary)
    return summary


def main(argv=None) -> int:
    import wmrjax as w
    from wmrjax import references as R

    from wmrjax import cli

    p = common.parser(__doc__.splitlines()[0], "results/certify")
    p.add_argument("--robot", default="(2,0)", help="robot type: (2,0), (2,1), (1,1) or (1,2)")
    p.add_argument("--reference", default="paper_62", choices=sorted(R.REFERENCES), help="named reference")
    p.add_argument("--level", default="velocity", choices=["velocity", "torque"], help="velocity or torque level")
    p.add_argument("--poles", type=cli.positive, default=1.0, help="closed-loop poles at -POLES [1/s] (1: the paper's)")
    p.add_argument("--t-final", type=cli.positive, default=10.0, help="horizon [s]")
    p.add_argument("--eps", type=cli.positive, default=1e-2, help="Lemma 2's margin eps [zeta units: m, m/s]")
    p.add_argument("--dt", type=cli.positive, default=0.01, help="RK4 step of the empirical checks [s]")
    p.add_argument("--n-empirical", type=cli.count, default=4096, help="sampled initial errors (every K2 checked on them)")
    p.add_argument("--n-directions", type=cli.count, default=128, help="rays of the position-slice empirical radius")
    p.add_argument("--n-starts", type=cli.nonnegative_int, default=16,
                   help="falsifier gradient starts per radius (0: no falsifier)")
    p.add_argument("--heading-offset", type=cli.finite, default=None,
                   help="reference heading offset [rad] (crab angle; None: the type's default)")
    p.add_argument("--map-grid", type=cli.grid_size, default=81, help="slice map resolution (N x N runs)")
    p.add_argument("--geometry", type=cli.finite, nargs=3, default=None, metavar=("L", "E", "DELTA"),
                   help="robot geometry [m, m, rad] (None: the paper's along paper_62/66 where it has one, "
                        "else the type's default)")
    p.add_argument("--devices", type=cli.count, default=os.cpu_count() or 1,
                   help="JAX host devices the batch simulations are spread over (one per core; sets XLA_FLAGS "
                        "before JAX starts its backend)")
    a = p.parse_args(argv)
    flag = f"--xla_force_host_platform_device_count={a.devices}"
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()   # read when the backend starts
    cli.check_horizon(p, t_final=a.t_final, dt=a.dt, batch=max(a.n_empirical, a.map_grid ** 2), saved_every=10)
    try:
        w.robot_type(a.robot)
        setup(a.robot, a.reference, a.level, a.poles, a.heading_offset, a.geometry)   # geometry, reference: now
    except ValueError as e:
        p.error(str(e))
    s = cli.work(p, a, lambda progress: run(a.out, a.robot, a.reference, a.level, a.poles, a.t_final, a.eps, a.dt,
                                            a.n_empirical, a.n_directions, a.n_starts, a.heading_offset,
                                            a.map_grid, geometry=a.geometry, progress=progress))
    keys = ["radius_paper", "radius_lyapunov", "radius_exact_norm", "radius_exact_map", "radius_exact_map_position_slice",
            "empirical_radius_position_slice"]
    print("  ".join(f"{k} {s[k]:.4f}" for k in keys if s.get(k) is not None))
    print(f"falsified full {s['falsified_full']['radius']}, position slice {s['falsified_position_slice']['radius']}; "
          f"wrote {a.out}/summary.json and slice_map.png in {s['wall_time_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
