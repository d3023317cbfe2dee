"""The certification job (``wmrjax certify``): the ``[certify]`` section, the problem's one dynamic
closed loop, :func:`wmrjax.certify.analyse` on it (Lemma 2 three ways, the exact map, the
empirical and falsified radii, the problem loop's falsified radius), the slice map, and
``summary.json`` with what each radius covers and whether it is proved or estimated."""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _files as files
from wmrjax import certify as C
from wmrjax.problem import Law, Problem, ProblemError, Setting, check_keys, integer, nonnegative, positive
from wmrjax.report import JobReport

CERTIFY_KEYS = {
    "eps": 1e-2,
    "n_empirical": 4096,
    "n_directions": 128,
    "n_starts": 16,
    "map_grid": 81,
    "seed": 0,
    "budget": 0.0,
    "noise_bound": 3.0,
}
"""The ``[certify]`` keys and their defaults (eps [output-error units: m, m/s]; budget [s], 0:
none), written once."""
# the fewest random directions a budget scales the problem loop's falsifier to, and the fewest
# points per side of the slice map
PLANT_DIRECTIONS_FLOOR, MAP_GRID_FLOOR = 4, 11


def settings(problem) -> dict:
    """The ``[certify]`` section of a problem over its defaults (:func:`read_section`)."""
    return read_section(problem.data)


def read_section(data: dict) -> dict:
    """The ``[certify]`` section of a problem's data over :data:`CERTIFY_KEYS`, checked key by key
    (the schema :data:`wmrjax.problem.JOB_SECTIONS` validates at load)."""
    c = data.get("certify", {})
    check_keys("certify", c, tuple(CERTIFY_KEYS))
    out = dict(CERTIFY_KEYS)
    for k, v in c.items():
        if k == "eps":
            out[k] = positive("certify", k, v)
        elif k == "budget":
            out[k] = nonnegative("certify", k, v)
        elif k == "noise_bound":
            out[k] = positive("certify", k, v)
        else:
            out[k] = integer("certify", k, v, {"n_empirical": 0, "n_starts": 0, "seed": 0, "map_grid": 2}.get(k, 1))
    return out


def setup(problem, case=None):
    """``(setting, ctrl, params)`` of the problem's one closed loop to certify (a dynamic law)."""
    setting = problem.setting("certification", case=case)
    if setting.law != Law.DYNAMIC:
        raise ProblemError(
            'certification needs a dynamic linearizing law ([controller] law = "dynamic"): Lemma 2 '
            "and the exact map are about Table 4's closed loops"
        )
    # the certificates are the nominal loop's: a listed [plant] (a swept geometry range) is reported, not refused
    setting.check_single("certification", keep=("initial", "plant"))
    return setting, setting.ctrl, setting.params()


def slice_map(ctrl, params, block, path, *, t_final, dt, eps, n_grid=81, title=""):
    """PNG: log10 min_t dist over a grid of initial position errors, eps contour, certified circles."""
    R = 1.25 * max(v for k, v in block.items() if k.startswith("radius_") and v is not None)
    xs = np.linspace(-R, R, n_grid)
    X, Y = np.meshgrid(xs, xs)
    P = np.asarray(C.slice_basis(ctrl, C.Slice.POSITION))
    errs = np.stack([X.ravel(), Y.ravel()], 1) @ P.T
    d, s = C.min_distance(ctrl, params, t_final=t_final, initial_errors=jnp.asarray(errs), dt=dt)
    d = np.where(np.asarray(s), 0.0, np.asarray(d)).reshape(X.shape)
    plt = files.headless_pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    im = ax.pcolormesh(X, Y, np.log10(np.maximum(d, 1e-6)), cmap="viridis", shading="auto")
    fig.colorbar(
        im,
        ax=ax,
        label="log10 min_t dist(zeta(t), singular set)"
        if C.singular_rows(ctrl)
        else "log10 min_t dist(zeta(t), singular set) (capped at 1)",
    )
    bad = d < eps
    if bad.any():
        ax.plot(X[bad], Y[bad], "rs", ms=2.5, label=f"unsafe: comes within eps = {eps}")
    th = np.linspace(0, 2 * np.pi, 200)
    for i, (k, lab) in enumerate(
        [
            ("radius_paper", "Lemma 2, K2 of (64)"),
            ("radius_lyapunov", "Lemma 2, Lyapunov K2"),
            ("radius_exact_norm", "Lemma 2, K2 = ||exp(At)||"),
            ("radius_exact_map_position_slice", "exact map (position slice)"),
            ("empirical_radius_position_slice", "empirical (position slice)"),
        ]
    ):
        r = block.get(k)
        if r is not None:
            ax.plot(
                r * np.cos(th),
                r * np.sin(th),
                color=f"C{i + 1}",
                lw=1.4,
                ls="--" if "empirical" in k else "-",
                label=f"{lab}: {r:.3g}",
            )
    ax.set_xlabel("initial error in x_P [m]")
    ax.set_ylabel("initial error in y_P [m]")
    ax.set_title(title or "initial position errors (velocities = reference's)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="upper right")
    files.write_png(fig, path)
    plt.close(fig)
    return {"n_grid": n_grid, "half_width": R, "fraction_unsafe": float(bad.mean())}


@dataclasses.dataclass(frozen=True)
class CertifyReport(JobReport):
    """What :func:`run` found: the nominal loop's radii, the problem loop's certificate, the
    slice map, and what it cost.

    Attributes:
        problem: the problem certified.
        case: the case certified (``None``: the problem has none).
        settings: the ``[certify]`` section over its defaults (:data:`CERTIFY_KEYS`).
        setting: the problem's one closed loop (:meth:`wmrjax.problem.Problem.setting`).
        params: its parameters (geometry, reference, gains).
        nominal: :func:`wmrjax.certify.analyse`'s report: Lemma 2 three ways, the exact map,
            the empirical and falsified radii, every one the nominal continuous loop's.
        problem_certificate: per slice (``"full"``, ``"position"``) the certificate that covers the
            problem's plant, with what it covers, its kind and the real loop's falsified radius
            (:func:`wmrjax.certify.problem_certificate`; the nominal one for a problem without
            ``[plant]``).
        slice_map: the map's grid side, half-width [m] and fraction of its initial errors that
            come within eps of the singular set.
        estimate: the work estimate beside the measured stage times and peak memory.
        wall_time_s: the job's wall time [s].
        timing: per progress message, the seconds of work behind it.
    """

    problem: Problem
    case: str | None
    settings: dict
    setting: Setting
    params: object
    nominal: C.CertificationReport
    problem_certificate: dict
    slice_map: dict
    estimate: dict
    wall_time_s: float
    timing: list

    @property
    def alarms(self) -> list[str]:
        """Results that contradict the theory (a certified radius above a falsified one), the
        nominal loop's and the problem loop's: errors, not certificates."""
        return list(self.nominal.alarms) + C.real_loop.problem_alarms(self.problem_certificate)

    @property
    def warnings(self) -> list[str]:
        """What the problem's certificate does not cover, said in words."""
        return C.real_loop.plant_warnings(self.problem_certificate)

    def summary(self) -> dict:
        """``summary.json``: the problem, the loop, every radius labelled, the problem's certificate,
        the slice map, the estimate and the timing (plain JSON)."""
        s = _summary(self, self.nominal.summary())
        s["slice_map"] = self.slice_map
        s["estimate"] = self.estimate
        s["wall_time_s"] = self.wall_time_s
        s["timing"] = self.timing
        return files.jsonable(s)


def run(out, problem, case=None, progress=None) -> CertifyReport:
    """Certify the problem's closed loop; writes ``summary.json`` and ``slice_map.png`` in ``out``.

    Args:
        out: the output directory (``Path``; made if missing).
        problem: the problem (:class:`wmrjax.problem.Problem`) with a dynamic law.
        case: the case to certify, for a problem with cases.
        progress: called with each progress message (default: printed).

    Returns:
        the :class:`CertifyReport`.
    """
    report_progress = progress or (lambda msg: print(msg, flush=True))
    stages = []  # (message, time): the timing block charges each stretch to the message ending it
    started = time.perf_counter()

    def say(msg):
        stages.append((msg, time.perf_counter()))
        report_progress(msg)

    jax.config.update("jax_enable_x64", True)  # the job runs in float64
    t0 = time.time()
    cfg = settings(problem)
    setting, ctrl, params = setup(problem, case)
    t_final, dt = setting.t_final, setting.dt
    say(f"certify {ctrl.robot.name} ({ctrl.level}) along {setting.reference.name}, T = {t_final} s, eps = {cfg['eps']}")

    later = cfg["map_grid"] ** 2 + (2 * C.planned_runs(setting) if setting.plant else 0)
    nominal = C.analyse(
        ctrl,
        params,
        t_final=t_final,
        eps=cfg["eps"],
        dt=dt,
        n_empirical=cfg["n_empirical"],
        n_directions=cfg["n_directions"],
        n_starts=cfg["n_starts"],
        seed=cfg["seed"],
        budget_s=max(cfg["budget"] - (time.time() - t0), 1e-3) if cfg["budget"] else 0.0,
        later_runs=later,
        log=say,
    )
    map_grid, plant_directions = _sizes(cfg, nominal.estimate.scale)
    t_later = time.perf_counter()
    problem_block = C.problem_certificate(
        setting,
        params,
        {C.Slice.FULL: nominal.exact_full, C.Slice.POSITION: nominal.exact_position},
        eps=cfg["eps"],
        falsified={C.Slice.FULL: nominal.falsified_full, C.Slice.POSITION: nominal.falsified_position},
        seed=cfg["seed"],
        log=say,
        noise_bound=cfg["noise_bound"],
        n_directions=plant_directions,
    )
    say(f"slice map ({map_grid} x {map_grid} runs)")
    out.mkdir(parents=True, exist_ok=True)
    the_map = slice_map(
        ctrl,
        params,
        nominal.summary(),
        out / "slice_map.png",
        t_final=t_final,
        dt=dt,
        eps=cfg["eps"],
        n_grid=map_grid,
        title=f"{ctrl.robot.name} along {setting.reference.name}: initial position errors",
    )
    measured = dict(nominal.stage_s) | {"later runs": time.perf_counter() - t_later}
    estimate = nominal.estimate.summary(measured) | {
        "sizes_used": {"map_grid": map_grid, "plant_directions": plant_directions},
        "measured_peak_rss_bytes": C.budget.peak_resident_bytes(),  # beside the estimate's memory
    }
    wall, timing = time.time() - t0, _timing(stages, started, time.perf_counter())
    report = CertifyReport(problem, case, cfg, setting, params, nominal, problem_block, the_map, estimate, wall, timing)
    report.write_summary(out)
    return report


def _sizes(cfg: dict, scale: float) -> tuple[int, int]:
    """``(map_grid, plant_directions)`` scaled to a time budget (``scale`` 1: none): the map's runs
    scale with its side squared; a side asked below the floor stays as asked."""
    map_grid = min(cfg["map_grid"], max(MAP_GRID_FLOOR, round(cfg["map_grid"] * scale**0.5)))
    return map_grid, max(PLANT_DIRECTIONS_FLOOR, round(C.real_loop.N_DIRECTIONS * scale))


def _summary(r: CertifyReport, block: dict) -> dict:
    """``summary.json`` but the slice map, the estimate and the timing: the problem, the loop
    certified, every radius (``block``: the nominal loop's, labelled) and the problem loop's
    certificate."""
    problem, setting, params, problem_block = r.problem, r.setting, r.params, r.problem_certificate
    ctrl, gains = setting.ctrl, params.gains
    return {
        "experiment": "certify",
        "problem_name": problem.title,
        "case": r.case,
        "problem": problem.resolved(),
        "certify": r.settings,
        "robot": ctrl.robot.name,
        "level": str(ctrl.level),
        "reference": setting.reference.name,
        "heading_offset": float(params.reference.heading_offset),
        "geometry": {k: float(v) for k, v in params.geometry._asdict().items()},
        "gains": C.plain({"coefficients": gains.coeffs} if not gains.time_varying else {"schedule_knots": gains.times}),
        "closed_loop_poles_re_im": None
        if gains.time_varying
        else [[float(p.real), float(p.imag)] for p in ctrl.error_poles(gains)],
        "plant": (
            "every radius but problem_certificate's falsified ones is the nominal continuous loop's "
            "(radius_labels); problem_certificate is the problem's loop's"
            if setting.plant
            else None
        ),
        "dt": setting.dt,
        **block,
        "radius_labels": C.radius_labels(block),
        "problem_certificate": problem_block,
        "plant_warnings": r.warnings,
        "alarms": r.alarms,
    }


def _timing(stages, start: float, end: float) -> list:
    """Seconds between consecutive progress messages, each charged to the later one (the
    pipeline reports a stage when it ends: the time is the work behind that line, compiling
    included); a last entry for what follows the last message."""
    times = [start] + [t for _, t in stages] + [end]
    names = [msg for msg, _ in stages] + ["after the last message (figure, summary)"]
    return [{"stage": m, "seconds": round(b - a, 3)} for m, a, b in zip(names, times[:-1], times[1:])]
