"""The experiment entry points run and write what the README promises."""

import json
import os
import subprocess
import sys

import numpy as np

from experiments import section_6_1

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_section_6_1_outputs(tmp_path):
    s = section_6_1.run(tmp_path, dt=0.01, t_final=10.0, n_empirical=64)
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
