"""The probe's command line: run every case (or those whose id contains ``--only``) against one
tree and write ``OUT/summary.json`` and ``OUT/cases.md``."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.probe import harness

DOC = """Probe a wmrjax tree with bad and hostile inputs: every case runs in a fresh process with the
tree first on PYTHONPATH (any checkout, old or new), and is classified GOOD (refused clearly and
early, or the right answer), POOR (refused late or unclearly) or BAD (data lost, mixed results, a
silently wrong answer, or a hang where a refusal was due). Writes OUT/summary.json and OUT/cases.md."""


def parser() -> argparse.ArgumentParser:
    """The probe's options."""
    p = argparse.ArgumentParser(prog="python -m tests.probe", description=DOC)
    p.add_argument("--tree", type=Path, required=True, help="the checkout to probe (its root: wmrjax/, tests/ ...)")
    p.add_argument("--out", type=Path, required=True, help="output directory (summary.json, cases.md)")
    p.add_argument(
        "--only", default=None, help="run only the cases whose id contains this text (several: separated by commas)"
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=120.0,
        help="CPU seconds a case's processes may use unless it sets its own (default: 120)",
    )
    p.add_argument(
        "--wall-factor",
        type=float,
        default=4.0,
        help="a case is also stopped after this many times its timeout in wall seconds (default: 4)",
    )
    p.add_argument(
        "--memory-limit",
        type=float,
        default=6.0,
        help="address-space limit of every process of a case [GB] (default: 6): a case that would "
        "allocate more fails instead of exhausting the machine",
    )
    p.add_argument("--keep", action="store_true", help="keep the cases' directories (printed at the end)")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    return p


def all_cases() -> list:
    """Every case, in the order they run."""
    from tests.probe import cases_data, cases_files, cases_outputs, cases_resources, cases_unclear, cases_wrong

    cases = []
    for module in (cases_data, cases_wrong, cases_resources, cases_unclear, cases_files, cases_outputs):
        cases += module.cases()
    ids = [c.id for c in cases]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"case ids listed twice: {dup}")
    bad = sorted({c.category for c in cases} - set(harness.CATEGORIES))
    if bad:
        raise ValueError(f"unknown categories: {bad}")
    return cases


def _commit(tree: Path) -> str | None:
    try:
        out = subprocess.run(
            ["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def totals(results: dict) -> dict:
    """Counts per outcome, per category and per category and outcome."""
    by_cat = {}
    by_outcome = {o: 0 for o in harness.OUTCOMES}
    for r in results.values():
        by_outcome[r["outcome"]] += 1
        row = by_cat.setdefault(r["category"], {o: 0 for o in harness.OUTCOMES})
        row[r["outcome"]] += 1
    order = [c for c in harness.CATEGORIES if c in by_cat]
    return {"cases": len(results), "by_outcome": by_outcome, "by_category": {c: by_cat[c] for c in order}}


def _atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def markdown(summary: dict) -> str:
    """``cases.md``: the totals per category and outcome, then one row per case."""
    t = summary["totals"]
    lines = [
        f"# Probe of `{summary['tree']}` ({(summary['commit'] or 'unknown')[:12]})",
        "",
        f"{t['cases']} cases in {summary['wall_seconds']:.0f} s; "
        + ", ".join(f"{o} {n}" for o, n in t["by_outcome"].items())
        + ("" if summary["complete"] else " (incomplete)"),
        "",
        "| category | GOOD | POOR | BAD |",
        "|---|---|---|---|",
    ]
    for cat, row in t["by_category"].items():
        lines.append(f"| {cat} | {row['GOOD']} | {row['POOR']} | {row['BAD']} |")
    lines += ["", "| id | category | issue | outcome | s | evidence |", "|---|---|---|---|---|---|"]
    for cid, r in summary["results"].items():
        evidence = r["evidence"] + (f" (note: {r['note']})" if r.get("note") else "")
        lines.append(
            f"| {_cell(cid)} | {r['category']} | {'yes' if r['issue'] else ''} | {r['outcome']} | "
            f"{r['seconds']:.1f} | {_cell(evidence)} |"
        )
    return "\n".join(lines) + "\n"


def write(out: Path, summary: dict) -> None:
    """Write summary.json and cases.md atomically."""
    _atomic(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    _atomic(out / "cases.md", markdown(summary))


def _record(case, outcome: str, evidence: str, run) -> dict:
    return {
        "category": case.category,
        "issue": case.issue,
        "outcome": outcome,
        "seconds": round(run.seconds, 2),
        "cpu_seconds": round(run.cpu_seconds, 2),
        "evidence": evidence,
        "description": case.description,
        "note": case.note,
    }


def main(argv=None) -> int:
    """Run the probe.

    Args:
      argv: the command line's arguments (default: ``sys.argv[1:]``).

    Returns:
      0 when every selected case ran, whatever their outcomes (a bad option exits 2).
    """
    p = parser()
    a = p.parse_args(argv)
    wanted = [w for w in (a.only or "").split(",") if w]
    cases = [c for c in all_cases() if a.only is None or any(w in c.id for w in wanted)]
    if a.list:
        for c in cases:
            print(f"{c.id:45s} {c.category:16s} {'issue ' if c.issue else ''}{c.description}")
        return 0
    tree = a.tree.resolve()
    if not (tree / "wmrjax" / "__init__.py").is_file():
        p.error(f"--tree {tree}: not a wmrjax checkout (no wmrjax/__init__.py)")
    if not cases:
        p.error(f"--only {a.only!r} selects no case")
    a.out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="wmrjax-probe-"))
    (work / "cases").mkdir()
    (work / "fixtures").mkdir()
    t0 = time.monotonic()
    summary = {
        "probe": "wmrjax bad and hostile inputs (issue 34)",
        "tree": str(tree),
        "commit": _commit(tree),
        "python": sys.executable,
        "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "timeout_cpu_s": a.timeout,
        "wall_factor": a.wall_factor,
        "memory_limit_gb": a.memory_limit,
        "only": a.only,
        "complete": False,
        "wall_seconds": 0.0,
        "totals": {},
        "results": {},
    }
    try:
        for i, case in enumerate(cases, 1):
            limit = case.timeout or a.timeout
            run = harness.execute(case, tree, work, limit, int(a.memory_limit * 2**30), a.wall_factor)
            outcome, evidence = harness.classify(case, run)
            summary["results"][case.id] = _record(case, outcome, evidence, run)
            summary["totals"] = totals(summary["results"])
            summary["wall_seconds"] = round(time.monotonic() - t0, 1)
            write(a.out, summary)
            print(f"[{i:3d}/{len(cases)}] {outcome:4s} {run.seconds:6.1f} s  {case.id}: {evidence[:150]}", flush=True)
        summary["complete"] = True
        write(a.out, summary)
    finally:
        if a.keep:
            print(f"case directories kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    t = summary["totals"]
    print(
        f"{t['cases']} cases in {summary['wall_seconds']:.0f} s: {t['by_outcome']}; wrote {a.out}/summary.json, cases.md"
    )
    return 0
