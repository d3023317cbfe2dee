"""The experiment entry points run and write what the README promises."""

import json

import numpy as np
import pytest

from paper import section_6_1


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
    assert sim["max_linear_error_residual"] < 1e-8
    # known values of the §6.1 run (M1 = 0.04 (10 - 2t)^2 + 1 has its minimum 1 at t = 5 s; (63): 0.54 sqrt 2)
    np.testing.assert_allclose(sim["min_eta1"], 1.000330910811918, rtol=1e-9)
    assert sim["t_min_eta1"] == 5.0
    np.testing.assert_allclose(sim["max_position_error"], 0.54 * np.sqrt(2.0), rtol=1e-4)
    np.testing.assert_allclose(sim["final_position_error"], 3.813788664680727e-4, rtol=1e-6)
    with np.load(tmp_path / "trajectories.npz", allow_pickle=False) as z:
        assert z["t"].shape == (1001,) and z["state"].shape == (1001, 4) and z["control"].shape == (1001, 2)
    l2 = on_disk["lemma2"]
    assert l2["condition_52"] is True and l2["eps"] == 0.01
    assert l2["zeta0_norm"] <= l2["radius_paper"] <= l2["radius_lyapunov"] <= l2["radius_exact_norm"]
    assert abs(l2["argmin_F"] - 3.92) < 0.05 and abs(l2["min_F"] - 0.768) < 1e-3
    assert abs(l2["radius_exact_map"] - 4.99) < 1e-9 and 8.7 < l2["radius_exact_map_position_slice"] < 8.9
    # the rays include the exact map's worst direction: simulation finds the same radius
    assert abs(l2["empirical_radius_position_slice"] - l2["radius_exact_map_position_slice"]) < 1e-2
    # no falsifier here (n_starts = 0, so no falsified radius: it is checked where it is computed,
    # tests/test_certify_tightness.py); every Lemma 2 radius lies below the exact map's, which the
    # simulated rays above confirm
    assert l2["falsified_full"] == {"radius": None, "skipped": "n_starts = 0"}
    assert max(l2[f"radius_{n}"] for n in ("paper", "lyapunov", "exact_norm")) <= l2["radius_exact_map"]
    for name in ("paper", "lyapunov", "exact_norm"):
        assert l2["empirical"][name]["violations_53_inside"] == 0 and l2["empirical"][name]["singular_inside"] == 0
    for fig in ["fig7_F.png", "fig8_paths.png", "fig9_errors.png"]:
        assert (tmp_path / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # and the numbers above are the figures' data
    assert s["simulation"] == on_disk["simulation"]


def test_certify_cli(tmp_path, returns, capsys):
    """The CLI writes every key and the map, prints the job's typed report and exits 0; (1,2)'s
    curved singular set is covered in test_certify."""
    from wmrjax.cli import certify
    from wmrjax.problem import Problem

    path = tmp_path / "p.toml"
    path.write_text(
        '[controller]\nlaw = "dynamic"\nrobot = "(2,1)"\n[reference]\nfamily = "circle"\n'
        '[initial]\nspace = "output"\n[simulation]\nt_final = 3.0\ndt = 0.02\n'
        "[certify]\nn_empirical = 16\nn_directions = 4\nn_starts = 0\nmap_grid = 5\n"
    )
    problem = Problem.load(path)
    reports = returns(certify, "run")
    out = tmp_path / "out"
    assert certify.main([str(path), "--out", str(out), "--no-compile-cache", "--devices", "1"]) == 0
    (s,) = reports
    printed = capsys.readouterr().out
    assert f"radius_exact_map_position_slice {s.nominal.exact_position.radius:.4f} (attained)" in printed
    tmp_path = out
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["m1"].startswith("closed form")
    assert 0 < on_disk["radius_lyapunov"] <= on_disk["radius_exact_norm"] <= on_disk["radius_exact_map"]
    assert on_disk["radius_exact_map"] <= on_disk["radius_exact_map_position_slice"]
    for k in ("lyapunov", "exact_norm"):
        assert on_disk["empirical"][k]["violations_53_inside"] == 0 and on_disk["empirical"][k]["singular_inside"] == 0
    assert (tmp_path / "slice_map.png").read_bytes()[:4] == b"\x89PNG" and s.slice_map["n_grid"] == 5
    # the typed report: its summary is plain JSON (it held arrays: TypeError) and is the file
    assert json.loads(json.dumps(s.summary())) == on_disk
    assert s.nominal.exact_position.radius == on_disk["radius_exact_map_position_slice"]
    assert on_disk["alarms"] == [] and s.alarms == []
    assert Problem.from_dict(on_disk["problem"]).resolved() == problem.resolved()
    assert on_disk["geometry"] == {"L": 1.0, "e": 0.0, "delta": 0.0} and on_disk["heading_offset"] == 0.3
    timing = on_disk["timing"]  # where the time went, stage by stage, adding up to the whole run
    assert len(timing) >= 5 and all(t["seconds"] >= 0 and t["stage"] for t in timing)
    assert any("Lemma 2" in t["stage"] for t in timing) and timing[-1]["stage"].startswith("after the last")
    assert sum(t["seconds"] for t in timing) == pytest.approx(on_disk["wall_time_s"], abs=0.5)
    assert timing[1]["stage"].strip().startswith("estimate: about")  # said before the stages ran
    est = on_disk["estimate"]  # every stage estimated, beside its measured time
    assert est["counts"] == {
        "n_empirical": 16,
        "n_directions": 4,
        "n_starts": 0,
        "n_samples": 512,
        "steps": 30,
        "later": 25,
    }
    assert est["scale"] == 1.0 and est["budget_s"] == 0.0 and est["sizes_used"]["map_grid"] == 5
    ran = {k: v for k, v in est["stages"].items() if not k.startswith("falsifier")}  # n_starts = 0: none
    assert all(v["estimated_s"] >= 0 and v["measured_s"] >= 0 for v in ran.values())
    assert all(v["estimated_s"] == 0 and v["measured_s"] is None for k, v in est["stages"].items() if k not in ran)
    assert est["measured_peak_rss_bytes"] > 0 and est["memory_bytes"] > 0
    with pytest.raises(SystemExit):
        certify.main(["--robot", "(9,9)", "--out", str(tmp_path)])
