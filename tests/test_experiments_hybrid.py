"""Experiment entry points (see README): they run and write what the README promises."""

import json
import math

import numpy as np


def test_section_6_2_outputs(tmp_path):
    from paper import section_6_2

    s = section_6_2.run(tmp_path, dt=0.02, t_final=15.0, n_batch=8)
    d = json.loads((tmp_path / "summary.json").read_text())
    assert d["switched"] and d["t_switch"] == s["t_switch"]
    np.testing.assert_allclose(d["t_switch"], 5.24, atol=1e-9)  # the first step inside the disk
    np.testing.assert_allclose(d["final_distance"], 0.011397245977841761, rtol=1e-6)
    np.testing.assert_allclose(d["eta1_at_switch"], 0.2367789264297342, rtol=1e-9)
    assert set(d["state_at_switch"]) == {"x", "y", "theta", "chi1"}
    assert math.hypot(d["state_at_switch"]["x"], d["state_at_switch"]["y"]) <= d["r_switch"]
    assert 0 < d["eta1_at_switch"] and 0 < d["min_eta1_before_switch"] and d["final_distance"] < 0.05
    assert d["lemma2"]["condition_52_exact_norm"] and not d["nonfinite"]
    assert d["batch"]["n_runs"] == 8 and d["batch"]["fraction_switched"] == 1.0 and d["batch"]["nonfinite"] == 0
    for f in ("fig10_paths.png", "fig11_eta1.png", "batch.png"):
        assert (tmp_path / f).read_bytes()[:4] == b"\x89PNG"
