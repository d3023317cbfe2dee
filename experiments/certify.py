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
has a closed form (a one-dimensional minimisation) but there is no exact-map radius, and the
empirical/falsifier measure is min_t |det K|.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time

from experiments import _common

DEFAULT_OFFSET = {"(2,0)": 0.0, "(2,1)": 0.3, "(1,1)": 0.0, "(1,2)": 0.5}


def setup(robot, reference, level="velocity", poles=1.0, heading_offset=None):
    import wmrjax as w
    from experiments.posture_tracking import geometry_for
    from wmrjax import references as R

    ctrl = w.dynamic_linearization(robot, level)
    ref = R.named(reference)
    off = DEFAULT_OFFSET[ctrl.robot.name] if heading_offset is None else heading_offset
    if off:
        ref = dataclasses.replace(ref, heading_offset=R._as_array(off))
    g = w.Geometry(e=0.0) if (ctrl.robot.name == "(2,0)" and reference == "paper_62") else geometry_for(ctrl.robot.name)
    return ctrl, ctrl.params(ref, poles=poles, geometry=g)


def analyse(ctrl, params, *, t_final, eps=1e-2, dt=0.01, n_empirical=4096, n_directions=256, n_starts=16,
            falsifier_dt=0.02, seed=0, zeta0_norm=None, log=print) -> tuple[dict, dict]:
    """Every radius of the certification issue for one closed loop; returns (summary block, figure data)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from wmrjax import certify as C

    n_steps = int(round(t_final / dt))
    t0 = time.time()
    cert = C.lemma2(ctrl, params, t_final, eps, n_t=n_steps + 1)
    A = ctrl.error_matrix(params.gains)
    k2s = {"lyapunov": lambda ts: C.k2_lyapunov(A, ts), "exact_norm": lambda ts: C.k2_exact(A, ts)}
    if "paper" in cert:
        k2s = {"paper": C.k2_paper, **k2s}
    block = {"eps": eps, "t_final": t_final, "m1": cert["m1_method"]}
    for name in k2s:
        block[f"radius_{name}"] = float(cert[name].radius)
        block[f"argmin_F_{name}"] = float(cert[name].argmin)
    if zeta0_norm is not None:
        ref = cert["paper"] if "paper" in cert else cert["exact_norm"]
        block.update(zeta0_norm=zeta0_norm, min_F=float(ref.radius), argmin_F=float(ref.argmin),
                     condition_52=bool(zeta0_norm <= float(ref.radius)))
    certified = max(block[f"radius_{n}"] for n in k2s)
    radii_txt = ", ".join(f"{n} {block['radius_' + n]:.4f}" for n in k2s)
    log(f"  Lemma 2 radii {radii_txt}  ({time.time() - t0:.0f} s)")

    exact = {}
    if C.singular_rows(ctrl) is not None:
        for b in ("full", "position"):
            em = C.exact_map_radius(ctrl, params, t_final, eps, basis=b, n_t=4 * n_steps + 1)
            exact[b] = em
            key = "radius_exact_map" + ("" if b == "full" else "_position_slice")
            block[key] = float(em.radius)
            block[key.replace("radius", "worst")] = {"t": float(em.argmin), "initial_error": np.asarray(em.worst_error)}
        log(f"  exact-map radius full {block['radius_exact_map']:.4f}, position slice "
            f"{block['radius_exact_map_position_slice']:.4f}  ({time.time() - t0:.0f} s)")
    else:
        block["radius_exact_map"] = block["radius_exact_map_position_slice"] = None
        block["exact_map_note"] = "singular set is curved for (1,2): no exact-map radius (see falsified radii)"
    r_top = max([certified] + [float(e.radius) for e in exact.values()])

    # -- empirical: (53) and regularity inside every ball
    key = jax.random.PRNGKey(seed)
    kd, kr, kf1, kf2 = jax.random.split(key, 4)
    emp = {"n_runs": n_empirical, "radius_range": [0.0, 2.0 * r_top], "sampling": "uniform direction, uniform radius"}
    if n_empirical:
        dirs = C.sample_sphere(kd, n_empirical, A.shape[0])
        errs = dirs * (2.0 * r_top * jax.random.uniform(kr, (n_empirical,)))[:, None]
        n0 = np.asarray(jnp.linalg.norm(errs, axis=1))
        for name, k2 in k2s.items():
            res = C.verify(ctrl, params, errs, k2, dt=dt, n_steps=n_steps, save_every=10)
            inside = n0 <= block[f"radius_{name}"]
            sing, viol = np.asarray(res["singular"]), np.asarray(res["violation_53"])
            emp[name] = {"runs_inside": int(inside.sum()), "violations_53_inside": int((viol & inside).sum()),
                         "singular_inside": int((sing & inside).sum()), "singular_total": int(sing.sum())}
            if (viol & inside).any() or (sing & inside).any():
                print(f"LEMMA 2 VIOLATED inside the {name} certificate: {emp[name]}", file=sys.stderr, flush=True)
        log(f"  empirical: {n_empirical} runs per K2, violations inside "
            f"{sum(emp[n]['violations_53_inside'] + emp[n]['singular_inside'] for n in k2s)}  ({time.time() - t0:.0f} s)")
    block["empirical"] = emp

    # -- empirical safe radius per direction of the position slice
    P = C.slice_basis(ctrl, "position")
    ang = np.linspace(0.0, 2.0 * math.pi, n_directions, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], 1)
    if "position" in exact:  # make sure the worst direction of the exact map is among the rays
        wd = np.asarray(P.T @ exact["position"].worst_error)
        ring = np.concatenate([ring, (wd / np.linalg.norm(wd))[None]])
    er = C.empirical_radius(ctrl, params, ring @ np.asarray(P).T, 2.0 * r_top, eps, dt=dt, n_steps=n_steps)
    block["empirical_radius_position_slice"] = er["radius"] if np.isfinite(er["radius"]) else None
    block["empirical_position_slice"] = {"n_directions": len(ring), "r_max": 2.0 * r_top, "n_runs": er["n_runs"],
                                         "fraction_of_directions_failing": float(np.isfinite(er["per_direction"]).mean()),
                                         "worst_direction": er["worst_direction"]}
    log(f"  empirical safe radius (position slice, {len(ring)} rays): {er['radius']:.4f}  ({time.time() - t0:.0f} s)")

    # -- gradient falsifier, full and position slice
    fs = {}
    for b, kf in (("full", kf1), ("position", kf2)) if n_starts else ():
        r_hi = 1.05 * float(exact[b].radius) if b in exact else 2.0 * certified
        f = C.falsified_radius(ctrl, params, eps, r_hi, kf, dt=falsifier_dt, n_steps=int(round(t_final / falsifier_dt)),
                               basis=b, n_starts=n_starts, r_lo=certified)
        fs[b] = f
        name = "falsified_full" if b == "full" else "falsified_position_slice"
        block[name] = {"radius": f["radius"], "initial_error": f["initial_error"], "distance": f["distance"],
                       "rollouts": f["rollouts"], "bracket": f.get("bracket")}
        log(f"  falsifier ({b}): smallest failing radius {f['radius']}  ({time.time() - t0:.0f} s)")
    if not n_starts:
        block["falsified_full"] = block["falsified_position_slice"] = {"radius": None, "skipped": "n_starts = 0"}
    radii = [block[f"radius_{n}"] for n in k2s] + [block["radius_exact_map"], block["radius_exact_map_position_slice"]]
    block["certified_below_falsified"] = all(
        r is None or b not in fs or fs[b]["radius"] is None or r <= fs[b]["radius"] + 1e-9
        for r, b in zip(radii, ["full"] * len(k2s) + ["full", "position"]))
    if not block["certified_below_falsified"]:
        print("A CERTIFIED RADIUS EXCEEDS A FALSIFIED ONE: a certificate is wrong", file=sys.stderr, flush=True)
    return block, {"cert": cert, "exact": exact, "k2s": list(k2s)}


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
    d, s = C.min_distance(ctrl, params, jnp.asarray(errs), dt=dt, n_steps=int(round(t_final / dt)), save_every=1)
    d = np.where(np.asarray(s), 0.0, np.asarray(d)).reshape(X.shape)
    plt = _common.pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    im = ax.pcolormesh(X, Y, np.log10(np.maximum(d, 1e-6)), cmap="viridis", shading="auto")
    fig.colorbar(im, ax=ax, label="log10 min_t dist(zeta(t), singular set)" if C.singular_rows(ctrl) else
                 "log10 min_t |det K|")
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
    _common.save_figure(fig, path)
    plt.close(fig)
    return {"n_grid": n_grid, "half_width": R, "fraction_unsafe": float(bad.mean())}


def run(out, robot="(2,0)", reference="paper_62", level="velocity", poles=1.0, t_final=10.0, eps=1e-2, dt=0.01,
        n_empirical=4096, n_directions=256, n_starts=16, heading_offset=None, map_grid=81, seed=0) -> dict:
    _common.enable_x64()
    t0 = time.time()
    ctrl, params = setup(robot, reference, level, poles, heading_offset)
    print(f"certify {ctrl.robot.name} ({level}) along {reference}, T = {t_final} s, eps = {eps}", flush=True)
    block, _ = analyse(ctrl, params, t_final=t_final, eps=eps, dt=dt, n_empirical=n_empirical,
                       n_directions=n_directions, n_starts=n_starts, seed=seed)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"experiment": "certify", "robot": ctrl.robot.name, "level": level, "reference": reference,
               "heading_offset": float(params.reference.heading_offset), "geometry": params.geometry._asdict(),
               "poles": poles, "dt": dt, **block}
    summary["slice_map"] = slice_map(ctrl, params, block, out / "slice_map.png", t_final=t_final, dt=dt, eps=eps,
                                     n_grid=map_grid, title=f"{ctrl.robot.name} along {reference}: initial position errors")
    summary["wall_time_s"] = time.time() - t0
    _common.write_json(out / "summary.json", summary)
    return summary


def main(argv=None) -> int:
    import wmrjax as w
    from wmrjax import references as R

    p = _common.parser(__doc__.splitlines()[0], "results/certify")
    p.add_argument("--robot", default="(2,0)", help="robot type: (2,0), (2,1), (1,1) or (1,2) (default (2,0))")
    p.add_argument("--reference", default="paper_62", help=f"named reference, one of {sorted(R.REFERENCES)}")
    p.add_argument("--level", default="velocity", choices=["velocity", "torque"])
    p.add_argument("--poles", type=float, default=1.0, help="closed-loop poles at -POLES (default 1, the paper's)")
    p.add_argument("--t-final", type=float, default=10.0, help="horizon [s]")
    p.add_argument("--eps", type=float, default=1e-2, help="Lemma 2's margin eps (default 0.01)")
    p.add_argument("--dt", type=float, default=0.01, help="RK4 step of the empirical checks [s]")
    p.add_argument("--n-empirical", type=int, default=4096, help="sampled initial errors per K2 (default 4096)")
    p.add_argument("--n-directions", type=int, default=256, help="rays of the position-slice empirical radius")
    p.add_argument("--n-starts", type=int, default=16, help="falsifier starts (default 16)")
    p.add_argument("--heading-offset", type=float, default=None, help="reference heading offset [rad] (crab angle)")
    p.add_argument("--map-grid", type=int, default=81, help="slice map resolution (default 81 x 81)")
    a = p.parse_args(argv)
    try:
        w.robot_type(a.robot)
        for k in ("poles", "t_final", "eps", "dt"):
            if not (math.isfinite(getattr(a, k)) and getattr(a, k) > 0):
                raise ValueError(f"--{k.replace('_', '-')} must be finite and > 0, got {getattr(a, k)}")
        s = run(a.out, a.robot, a.reference, a.level, a.poles, a.t_final, a.eps, a.dt, a.n_empirical,
                a.n_directions, a.n_starts, a.heading_offset, a.map_grid)
    except ValueError as e:
        p.error(str(e))
    keys = ["radius_paper", "radius_lyapunov", "radius_exact_norm", "radius_exact_map", "radius_exact_map_position_slice",
            "empirical_radius_position_slice"]
    print("  ".join(f"{k} {s[k]:.4f}" for k in keys if s.get(k) is not None))
    print(f"falsified full {s['falsified_full']['radius']}, position slice {s['falsified_position_slice']['radius']}; "
          f"wrote {a.out}/summary.json and slice_map.png in {s['wall_time_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
