"""The experiment entry points run and write what the README promises."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from experiments import section_6_1

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_section_6_1_outputs(tmp_path):
    s = section_6_1.run(tmp_path, dt=0.01, t_final=10.0, n_empirical=64, n_directions=8, n_starts=0)
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["simulation"]["dt"] == 0.01 and on_disk["simulation"]["t_final"] == 10.0
    init = on_disk["initial_state"]
    assert set(init) >= {"x", "y", "theta", "chi1", "xdot", "ydot"}
    # (63): 5.35 m, 6.43 m, -3.53 m/s, and the compensator on the reference's branch
    assert abs(init["x"] - 5.35) < 5e-3 and abs(init["y"] - 6.43) < 5e-3
    assert abs(init["xdot"] + 3.5355) < 1e-3 and abs(init["ydot"] + 3.5355) < 1e-3
    assert abs(init["chi1"] - 5.0) < 1e-9 and abs(init["theta"] - 3 * np.pi / 4) < 1e-12
    sim = on_disk["simulation"]
    for key in ["min_eta1", "t_min_eta1", "max_position_error", "final_position_error", "max_linear_error_residual"]:
        assert isinstance(sim[key], float)
    assert sim["max_linear_error_residual"] < 1e-8
    assert 1.0 <= sim["min_eta1"] < 1.01 and abs(sim["t_min_eta1"] - 5.0) < 0.02  # M1 = 0.04 (10 - 2t)^2 + 1
    assert sim["final_position_error"] < 1e-3 < sim["max_position_error"]
    with np.load(tmp_path / "trajectories.npz", allow_pickle=False) as z:
        assert z["t"].shape == (1001,) and z["state"].shape == (1001, 4) and z["control"].shape == (1001, 2)
    l2 = on_disk["lemma2"]
    assert l2["condition_52"] is True and l2["eps"] == 0.01
    assert l2["zeta0_norm"] <= l2["radius_paper"] <= l2["radius_lyapunov"] <= l2["radius_exact_norm"]
    assert abs(l2["argmin_F"] - 3.92) < 0.05 and abs(l2["min_F"] - 0.768) < 1e-3
    assert abs(l2["radius_exact_map"] - 4.99) < 1e-9 and 8.7 < l2["radius_exact_map_position_slice"] < 8.9
    # the rays include the exact map's worst direction: simulation finds the same radius
    assert abs(l2["empirical_radius_position_slice"] - l2["radius_exact_map_position_slice"]) < 1e-2
    assert l2["falsified_full"]["radius"] is None and l2["certified_below_falsified"]
    for name in ("paper", "lyapunov", "exact_norm"):
        assert l2["empirical"][name]["violations_53_inside"] == 0 and l2["empirical"][name]["singular_inside"] == 0
    for fig in ["fig7_F.png", "fig8_paths.png", "fig9_errors.png"]:
        assert (tmp_path / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert s["simulation"] == on_disk["simulation"]


def test_benchmark_cli_smoke(tmp_path):
    env = dict(os.environ, PYTHONPATH=ROOT)
    env.pop("XLA_FLAGS", None)
    r = subprocess.run([sys.executable, "-m", "experiments.benchmark", "--out", str(tmp_path), "--batches", "64",
                        "--reps", "1", "--grad-batch", "8", "--scipy-trajectories", "1", "--devices", "2"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "summary.json").read_text())
    row = s["rollout"]["64"]
    assert row["max_abs_diff_wmrjax_vs_numpy"] < 1e-9  # same closed loop as the NumPy oracle
    assert row["wmrjax_batch_map"] > 0 and row["numpy_vectorised"] > 0
    assert s["machine"]["jax_devices"] == 2
    assert s["gradient"]["grad_finite"] and s["gradient"]["max_abs_diff_reverse_vs_forward_mode"] < 1e-9


def test_posture_tracking_smoke(tmp_path):
    from experiments import posture_tracking

    s = posture_tracking.run(tmp_path, n_random=16, t_final=4.0, dt=0.02, kinds=("(2,1)",), levels=("velocity",))
    for level in ("velocity",):
        r = s["cases"][f"(2,1) {level}"]["random"]
        assert r["n_runs"] == 16 and r["fraction_references_regular"] == 1.0
        assert 0.0 <= r["fraction_converged"] <= 1.0 and r["fraction_flagged_singular"] == 0.0
        assert r["final_position_error_m"]["max"] < 0.5
    assert (tmp_path / "posture_21.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "summary.json").read_text())["cases"].keys() == s["cases"].keys()


def test_certify_cli_curved_singular_set(tmp_path):
    """(1,2): no exact map (curved singular set), numerical M1; the CLI still writes every key and the map."""
    from experiments import certify

    s = certify.run(tmp_path, robot="(1,2)", reference="circle", t_final=3.0, dt=0.02, n_empirical=16,
                    n_directions=4, n_starts=0, map_grid=5)
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["radius_exact_map"] is None and "curved" in on_disk["exact_map_note"]
    assert on_disk["m1"].startswith("numerical")
    assert 0 < on_disk["radius_lyapunov"] <= on_disk["radius_exact_norm"]
    for k in ("lyapunov", "exact_norm"):
        assert on_disk["empirical"][k]["violations_53_inside"] == 0 and on_disk["empirical"][k]["singular_inside"] == 0
    assert (tmp_path / "slice_map.png").read_bytes()[:4] == b"\x89PNG" and s["slice_map"]["n_grid"] == 5
    with pytest.raises(SystemExit):
        certify.main(["--robot", "(9,9)", "--out", str(tmp_path)])


def test_section_6_2_outputs(tmp_path):
    from experiments import section_6_2

    s = section_6_2.run(tmp_path, dt=0.02, t_final=15.0, n_batch=8)
    d = json.loads((tmp_path / "summary.json").read_text())
    assert d["switched"] and 5.0 < d["t_switch"] < 5.5 and d["t_switch"] == s["t_switch"]
    assert set(d["state_at_switch"]) == {"x", "y", "theta", "chi1"}
    assert math.hypot(d["state_at_switch"]["x"], d["state_at_switch"]["y"]) <= d["r_switch"]
    assert 0 < d["eta1_at_switch"] and 0 < d["min_eta1_before_switch"] and d["final_distance"] < 0.05
    assert d["lemma2"]["condition_52_exact_norm"] and not d["nonfinite"]
    assert d["batch"]["n_runs"] == 8 and d["batch"]["fraction_switched"] == 1.0 and d["batch"]["nonfinite"] == 0
    for f in ("fig10_paths.png", "fig11_eta1.png", "batch.png"):
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"


def test_static_tracking_smoke(tmp_path):
    from experiments import static_tracking

    s = static_tracking.run(tmp_path, n_random=8, t_final=6.0, dt=0.02, kinds=("(2,0)",), levels=("velocity",))
    r = s["cases"]["(2,0) velocity"]["random"]
    assert r["n_runs"] == 8 and r["fraction_flagged_singular"] == 0.0 and r["fraction_converged"] == 1.0
    assert abs(r["min_abs_det_K_over_runs"] - 0.3) < 1e-9          # e sin(delta), delta = pi/2
    assert r["max_norm_z3"]["max"] > 0 and s["cases"]["(2,0) velocity"]["circle"]["final_point_error_m"] < 1e-2
    assert (tmp_path / "static_20.png").read_bytes()[:4] == b"\x89PNG"
