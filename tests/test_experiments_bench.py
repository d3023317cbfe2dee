"""Experiment entry points (see README): they run and write what the README promises."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import benchmark as M

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_benchmark_cli_smoke(tmp_path):
    # the session's XLA flags (tests/conftest.py: optimization level 0; the benchmark replaces any
    # device count with its --devices): this checks the benchmark's values, not its speed (80 s in a test run -> 55 s alone, 65 s in a test run, at level 0)
    env = dict(os.environ, PYTHONPATH=ROOT)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks.benchmark",
            "--out",
            str(tmp_path),
            "--batches",
            "64",
            "--reps",
            "1",
            "--grad-batch",
            "8",
            "--grad-batches",
            "8",
            "--compile-types",
            "none",
            "--memory-batch",
            "0",
            "--scipy-trajectories",
            "1",
            "--devices",
            "2",
            "--no-memory-estimates",  # minutes of measurements at scale
            "--export-samples",
            "0",  # the exported steps: tests/test_export.py
            "--reference-batch",
            "4",
            "--reference-levels",
            "velocity",
            "--tuner-problems",  # none: the tuner's timing is the benchmark's, not this smoke's
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "summary.json").read_text())
    refs = s["reference_families"]["levels"]["velocity"]
    assert set(refs) == {"builtin", "samples_10hz", "samples_100hz"} and refs["builtin"]["run_over_builtin"] == 1.0
    for r in refs.values():  # the sampled path is the built-in one to interpolation error, no run fails
        assert r["max_abs_diff_final_state_vs_builtin"] < 1e-9 and r["failed"] == 0
    row = s["rollout"]["64"]
    assert row["max_abs_diff_wmrjax_vs_numpy"] < 1e-9  # same closed loop as the NumPy oracle
    assert row["wmrjax_batch_map"] > 0 and row["numpy_vectorised"] > 0
    assert s["machine"]["jax_devices"] == 2
    g, many = s["gradient"], s["gradient_many"]
    # the headline (batch_value_and_grad, per-example reverse) equals value_and_grad in both modes
    assert g["grad_finite"] and g["method"] == "wmrjax.batch_value_and_grad"
    assert set(g["max_abs_diff_vs_headline_gradient"]) == {"value_and_grad_forward", "value_and_grad_reverse"}
    assert max(g["max_abs_diff_vs_headline_gradient"].values()) < 1e-12
    assert max(many["max_abs_diff_vs_headline_gradient"].values()) < 1e-12
    assert g["abs_diff_value_vs_forward_pass"] < 1e-15
    assert (g["mode"], g["n_parameters"], many["mode"], many["n_parameters"]) == ("reverse", 4, "reverse", 64)
    assert many["grad_finite"] and set(s["gradient_by_batch"]) == {"8"} and "compile" not in s and "memory" not in s
    assert "tuner" not in s


def test_cold_start_rows_time_fresh_processes_and_refuse_unknown_jobs(tmp_path, capsys):
    """The cold-start block (#36): each job twice in a fresh process, the second reading the
    compilation cache the first wrote; a job name it does not know is refused before any work."""
    jobs = M.cold_start_jobs()
    assert {"section_6_1", "section_6_2", "s_path_certify", "tuning_car_schedule", "certify_(1,2)_figure_eight"} <= set(
        jobs
    )
    assert {n for n in jobs if n.startswith("sweep_")} == {"sweep_" + n for n in M.SWEEP_EXAMPLES}
    assert all(
        (Path(ROOT) / "wmrjax" / "examples" / f"{n}.toml").is_file() for n in M.SWEEP_EXAMPLES + M.TUNING_EXAMPLES
    )
    rows = M.cold_start_rows({"help": ["benchmarks.benchmark", "--help"]}, progress=lambda m: None)
    r = rows["help"]
    assert r["exit"] == 0 and r["cold_s"] > 0 and r["warm_s"] > 0 and r["compile_share"] < 1
    with pytest.raises(SystemExit):
        M.main(["--out", str(tmp_path / "b"), "--cold-start", "section_6_9"])
    assert "unknown job(s) ['section_6_9']" in capsys.readouterr().err and not (tmp_path / "b").exists()
