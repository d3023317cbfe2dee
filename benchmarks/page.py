"""The benchmarks page's tables, regenerated from the results files the benchmarks write.

    python -m benchmarks.page            # rewrite the generated tables of the pages (PAGES)
    python -m benchmarks.page --check    # exit 1 where a page and its records differ

A benchmark that has a table on the page records its current numbers with :func:`record`:
``benchmarks/records/NAME.json`` holds when, at which commit, on which machine and by which
command they were measured, and the rows. On the page, each generated table sits between
``<!-- generated: TABLE -->`` and ``<!-- end generated -->``; :data:`TABLES` says which results file
and which function render it. The text around a table (what is measured, what it means) is
written by hand; the numbers and their provenance are not. History stays in git.

JAX-free (the page is rendered in the docs' test without starting JAX).
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "benchmarks" / "records"
PAGES = (ROOT / "docs" / "benchmarks.md", ROOT / "docs" / "commands" / "certify.md")
"""The pages with generated tables."""
BLOCK = re.compile(r"(<!-- generated: (?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)


MEASURED = ("wmrjax", "benchmarks", "tests/identify_oracle.py", "pyproject.toml")
"""What a measurement runs: a change here, not yet committed, makes the record's commit ``+dirty``
(the docs, the tests and the records themselves do not)."""


def _commit() -> str:
    """The checkout's commit, ``+dirty`` where what is measured differs from it (:data:`MEASURED`)."""
    git = lambda *a: subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short=7", "HEAD") or "unknown"
    changed = git("status", "--porcelain", "--untracked-files=no", "--", *MEASURED, ":!benchmarks/records")
    return head + ("+dirty" if changed else "")


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        kib = int(Path("/proc/meminfo").read_text().split()[1])  # MemTotal, the first line
    except (OSError, ValueError, IndexError):
        return None
    return round(kib / 2**20, 1)


def machine(backend: str = "cpu") -> str:
    """This machine in words: cores, CPU, memory, the JAX backend and versions."""
    mem = _memory_gib()
    return (
        f"{os.cpu_count()}-core {platform.machine()} ({_cpu()})" + (f", {mem} GiB" if mem else "")
        + f"; JAX {importlib.metadata.version('jax')} on the {backend.upper() if backend != 'cpu' else 'CPU'}"
        + f", Python {platform.python_version()}"
    )  # fmt: skip


def record(name: str, *, command: str, backend: str = "cpu", **data) -> Path:
    """Write ``benchmarks/records/NAME.json``: the provenance (UTC date, commit, machine, command)
    and ``data`` (the rows of the benchmark's tables); returns the path.

    Args:
        name: the results file's name (the benchmark's).
        command: the command that measured it, as a user types it.
        backend: the JAX backend it ran on.
        **data: plain-JSON values (lists of row dicts).
    """
    out = {
        "date": datetime.datetime.now(datetime.timezone.utc).date().isoformat(),
        "commit": _commit(),
        "machine": machine(backend),
        "command": command,
        **data,
    }
    return _write(RECORDS / f"{name}.json", out)


def _write(path: Path, obj: dict) -> Path:
    """``obj`` as JSON at ``path``, atomically (a killed benchmark leaves the previous file whole)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(obj, indent=1) + "\n")
    tmp.replace(path)
    return path


def save(name: str, out: Path, *, record_too: bool, command: str, **data) -> None:
    """A benchmark's results: ``out/NAME.json`` (with this machine), and with ``record_too`` the
    page's record (:func:`record`).

    Args:
        name: the benchmark's name.
        out: its ``--out`` directory (made if missing).
        record_too: whether ``--record`` was given.
        command: the command that measured it, as a user types it.
        **data: plain-JSON values (lists of row dicts).
    """
    _write(out / f"{name}.json", data | {"machine": machine()})
    if record_too:
        record(name, command=command, **data)


def provenance(r: dict) -> str:
    """The line above a table: when, which commit, which machine, which command."""
    return f"Measured {r['date']}, commit `{r['commit']}`, {r['machine']}; command: `{r['command']}`."


# --- the tables ------------------------------------------------------------------------------


def sampled_path(r: dict) -> str:
    """``benchmarks/sampled_path.py``: load time and memory per number of samples and degree."""
    lines = ["| samples | degree | load [s] | peak RSS [MB] | off the circle [m] |", "|---|---|---|---|---|"]
    for row in r["rows"]:
        if "error" in row:
            lines.append(f"| {row['samples']:,} | {row['degree']} | refused: {row['error'][:80]} | | |")
        else:
            lines.append(
                f"| {row['samples']:,} | {row['degree']} | {row['load_s']:.2f} | {row['peak_rss_bytes'] / 1e6:.0f} | "
                f"{row['position_error_m']:.1e} |"
            )
    return "\n".join(lines)


def identify_timing(r: dict) -> str:
    """``benchmarks/identify.py``, the fit's time: cold, warm, the whole process."""
    t = r["timing"]
    return (
        "| fit, cold [s] | fit, warm [s] | whole process [s] | iterations |\n|---|---|---|---|\n"
        f"| {t['cold_s']:.1f} | {t['warm_s']:.1f} | {t['process_s']:.1f} | {t['iterations']} |"
    )


def _by_parameter(rows, cell) -> str:
    """A table of parameters (rows) by robot and level (columns); ``cell(row)`` fills it, "—"
    where the robot has no such parameter or the logs do not determine it."""
    robots = list(dict.fromkeys(f"{x['robot']} {x['level']}" for x in rows))
    of = lambda k: [x["parameter"] for x in rows if f"{x['robot']} {x['level']}" == k]
    # the order of the robot with the most parameters, then any the others add
    params = list(dict.fromkeys(max((of(k) for k in robots), key=len) + [x["parameter"] for x in rows]))
    at = {(f"{x['robot']} {x['level']}", x["parameter"]): x for x in rows}
    lines = ["| parameter | " + " | ".join(robots) + " |", "|---" * (len(robots) + 1) + "|"]
    for p in params:
        cells = [cell(at[(k, p)]) if (k, p) in at else "—" for k in robots]
        lines.append(f"| {p} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def identify_coverage(r: dict) -> str:
    """Per parameter and robot: the 95 % interval's coverage, then the sd of (estimate − truth) /
    standard error over the seeds."""
    return _by_parameter(
        r["coverage"], lambda x: f"{x['coverage']:.0%}, {x['sd_of_z']:.2f}" if "coverage" in x else "—"
    )


def identify_bootstrap(r: dict) -> str:
    """Per parameter and robot: the bootstrap's sd over the Hessian's standard error."""
    return _by_parameter(r["bootstrap"], lambda x: f"{x['bootstrap_sd'] / x['hessian_std_error']:.2f}")


def certify_cost_times(r: dict) -> str:
    """``benchmarks/certify_cost.py``: ``wmrjax certify`` with and without the problem's ``[plant]``."""
    lines = ["| problem | plant | with `[plant]` [s] | without [s] | ratio |", "|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(
            f"| `{x['problem']}` | {', '.join(x['plant'])} | {x['with_plant_s']:.1f} | {x['without_plant_s']:.1f} | "
            f"{x['with_plant_s'] / x['without_plant_s']:.2f} |"
        )
    return "\n".join(lines)


def certify_cost_radii(r: dict) -> str:
    """Per problem and slice: the nominal loop's proved and falsified radii, the saturation-free
    radius, the problem's certificate (what covers its plant) and the real loop's falsified radius;
    the nominal proved radius over the real loop's falsified one (above 1: the nominal
    certificate is contradicted by the problem's own loop). The saturation-free radius is computed
    where limits are the plant's only feature ("—" otherwise)."""
    f = lambda v: "none" if v is None else f"{v:.4f}"
    lines = [
        "| problem (plant) | slice | nominal, proved | nominal, falsified | saturation-free, proved | "
        "problem's loop, proved | problem's loop, falsified | nominal proved / problem's falsified |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for x in r["rows"]:
        for i, (b, c) in enumerate(x["slices"].items()):
            label = f"`{x['problem']}` ({', '.join(x['plant'])})" if i == 0 else ""
            cert = f(c["problem_certificate"]) + (f" ({', '.join(c['covers'])})" if c["problem_certificate"] else "")
            ratio = c["nominal_exact_map"] / c["falsified"] if c["falsified"] else None
            shown = "—" if ratio is None else (f"**{ratio:.3f}**" if ratio > 1 else f"{ratio:.3f}")
            lines.append(
                f"| {label} | {b} | {f(c['nominal_exact_map'])} | {f(c['nominal_falsified'])} | "
                f"{'—' if c['saturation_free'] is None else f(c['saturation_free'])} | {cert} | {f(c['falsified'])} | "
                f"{shown} |"
            )
    return "\n".join(lines)


TABLES = {
    "sampled_path": ("sampled_path", sampled_path, True),
    "identify_timing": ("identify", identify_timing, True),
    "identify_coverage": ("identify", identify_coverage, False),
    "identify_bootstrap": ("identify", identify_bootstrap, False),
    "certify_cost_times": ("certify_cost", certify_cost_times, True),
    "certify_cost_radii": ("certify_cost", certify_cost_radii, True),
}
"""Table name on the page -> (results file, renderer, whether the provenance line leads it)."""


def render(name: str) -> str:
    """The generated text of table ``name``: its provenance line (where it leads) and the table."""
    if name not in TABLES:
        raise ValueError(f"docs/benchmarks.md names a table {name!r} that benchmarks/page.py does not know")
    file, fn, lead = TABLES[name]
    path = RECORDS / f"{file}.json"
    if not path.is_file():
        raise ValueError(f"table {name!r}: no record {path.relative_to(ROOT)}; run its benchmark with --record")
    r = json.loads(path.read_text())
    return (provenance(r) + "\n\n" if lead else "") + fn(r) + "\n"


def regenerate(text: str) -> str:
    """``text`` (the page) with every generated table rendered from its results file."""
    return BLOCK.sub(lambda m: m.group(1) + "\n" + render(m.group("name")) + "\n" + m.group(4), text)


def main(argv=None) -> int:
    """Rewrite the pages (or, with ``--check``, say where they differ from their records)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 where a page differs from its records")
    a = p.parse_args(argv)
    stale = []
    for page in PAGES:
        text = page.read_text()
        new = regenerate(text)
        if new != text:
            stale.append(str(page.relative_to(ROOT)))
            if not a.check:
                page.write_text(new)
    if a.check and stale:
        print(f"{', '.join(stale)}: differ from benchmarks/records: run python -m benchmarks.page")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
