"""What certifying a problem's own loop costs and what it proves (issue 54): ``wmrjax certify``
on the shipped problems with a ``[plant]``, cold, then the same file without its ``[plant]``.

    python -m benchmarks.certify_cost [--problems s_path steered_21 car_waypoints] [--record]

Each run is a fresh process with no persistent compilation cache, the file's ``[certify]``
counts, the examples copied into a scratch directory (the file without ``[plant]`` is written
there, beside the paths it names). Per problem: the wall time of both processes and their
ratio, and per slice the radii of ``summary.json``: the nominal exact map (proved), the
saturation-free radius (proved, where the plant has limits), the problem's certificate (the one
that covers the plant, or none) and the real loop's falsified radius (estimated).
Writes ``certify_cost.json`` into ``--out``; ``--record``: the page's record too
(``benchmarks/records/certify_cost.json``, rendered into docs/benchmarks.md by :mod:`benchmarks.page`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import page
from wmrjax.cli import machine
from wmrjax.identify.sections import with_plant_section

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "wmrjax" / "examples"
PROBLEMS = ("s_path", "steered_21", "car_waypoints")


def certify(path: Path, out: Path) -> dict:
    """``wmrjax certify PATH`` in a fresh process: its wall time and ``summary.json``."""
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "wmrjax", "certify", str(path), "--out", str(out), "--no-compile-cache"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    # 1: an alarm, which the summary records; never a traceback
    if r.returncode not in (0, 1) or "Traceback (most recent call last)" in r.stderr:
        raise RuntimeError(f"wmrjax certify {path.name} failed ({r.returncode}): {r.stderr[-2000:]}")
    return {"wall_s": wall, "summary": json.loads((out / "summary.json").read_text())}


def _radius(block):
    return None if block is None else block.get("lower_bound", block.get("radius"))


def row(name: str, real: dict, nominal: dict) -> dict:
    """The record's row of one problem: times and, per slice, the radii."""
    s = real["summary"]
    pc = s["problem_certificate"]
    slices = {}
    for b, key in (("full", "falsified_full"), ("position", "falsified_position_slice")):
        c = pc[b]
        slices[b] = {
            "nominal_exact_map": c["nominal_radius"],
            "nominal_falsified": (s.get(key) or {}).get("radius"),
            "saturation_free": _radius(c.get("saturation_free")),
            "problem_certificate": c["radius"],
            "covers": c["covers"],
            "not_covered": c.get("not_covered", []),
            "falsified": c["falsified_radius"],
        }
    return {
        "problem": name,
        "plant": pc["loop"],
        "with_plant_s": real["wall_s"],
        "without_plant_s": nominal["wall_s"],
        "job_with_plant_s": s["wall_time_s"],
        "job_without_plant_s": nominal["summary"]["wall_time_s"],
        "alarms": s["alarms"],
        "slices": slices,
    }


def main(argv=None) -> int:
    """Certify each problem with and without its plant; print and write the rows."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    p.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "certify_cost")
    p.add_argument(
        "--record", action="store_true", help="write the page's record (benchmarks/records/certify_cost.json)"
    )
    a = p.parse_args(argv)
    machine.configure_xla()  # as every command line that imports the package (its runs are child processes)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "examples"
        shutil.copytree(EXAMPLES, work)
        for name in a.problems:
            real = work / f"{name}.toml"
            bare = work / f"{name}_without_plant.toml"
            bare.write_text(with_plant_section(real.read_text(), ""))
            print(f"{name}: certifying with its [plant], then without", flush=True)
            r = row(name, certify(real, Path(tmp) / f"{name}_real"), certify(bare, Path(tmp) / f"{name}_bare"))
            rows.append(r)
            print(page.certify_cost_times({"rows": [r]}).splitlines()[-1], flush=True)
    print(page.certify_cost_times({"rows": rows}))
    print(page.certify_cost_radii({"rows": rows}))
    page.save(
        "certify_cost", a.out, record_too=a.record, command="python -m benchmarks.certify_cost --record", rows=rows
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
