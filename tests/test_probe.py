"""The probe of bad and hostile inputs (tests.probe): its oracles' classification on made-up
runs, its case list, and two cheap cases through its command line against this checkout (the
whole probe runs for minutes: it is run by hand, see docs/commands/probe.md)."""

import json
import subprocess
import sys
from pathlib import Path

from tests.probe import cli, harness, oracles

ROOT = Path(__file__).resolve().parents[1]


def _run(**kw):
    base = dict(
        rc=0, stdout="", stderr="", seconds=1.0, timed_out=False, dir=ROOT, results={}, exc=None, warnings=[], events=[]
    )
    return harness.Run(**(base | kw))


def _exc(kind="ValueError", message="dt must be > 0", value_error=True, traced=False):
    return {"type": kind, "module": "builtins", "value_error": value_error, "message": message, "traced": traced}


def test_library_refusals_are_classified():
    oracle = oracles.refuses(r"dt must be")
    assert oracle(_run(rc=1, exc=_exc()))[0] == "GOOD"
    assert oracle(_run(rc=1, exc=_exc(traced=True)))[0] == "POOR"  # late: after a time loop was traced
    assert oracle(_run(rc=1, exc=_exc(message="something else")))[0] == "POOR"  # not naming the cause
    assert oracle(_run(rc=1, exc=_exc("TypeError", value_error=False)))[0] == "POOR"  # a raw TypeError
    assert oracle(_run(rc=-6, stderr="terminate called after throwing std::bad_alloc"))[0] == "POOR"  # a C++ abort
    assert oracle(_run(rc=0, results={"failed": False}))[0] == "BAD"  # accepted: silently wrong
    assert oracle(_run(rc=None, timed_out=True))[0] == "BAD"  # a hang where a refusal was due
    check = oracles.answer(lambda r: (r["x"] == 1, f"x = {r['x']}"))
    assert check(_run(results={"x": 1})) == ("GOOD", "x = 1")
    assert check(_run(results={"x": 2}))[0] == "BAD"


def test_command_line_refusals_are_classified():
    oracle = oracles.cli_refuses(r"not a regular file")
    said = "usage: x\nx: error: 'g.json': not a regular file\n"
    assert oracle(_run(rc=2, stderr=said))[0] == "GOOD"
    assert oracle(_run(rc=1, stderr="Traceback (most recent call last):\nIsADirectoryError: g.json"))[0] == "POOR"
    assert oracle(_run(rc=2, stderr=said, events=[{"event": "trace"}]))[0] == "POOR"  # refused after the work started
    assert oracle(_run(rc=2, stderr=said, cpu_seconds=harness.LATE_CPU_S + 1))[0] == "POOR"
    assert oracle(_run(rc=0, stderr="done"))[0] == "BAD"
    # a trace before arm() (the case's own set-up) does not make a refusal late
    assert not _run(events=[{"event": "trace"}, {"event": "arm"}]).traced


def test_the_cases_are_complete_and_distinct():
    cases = cli.all_cases()
    assert len(cases) >= 150 and len({c.id for c in cases}) == len(cases)
    assert {c.category for c in cases} == set(harness.CATEGORIES)
    assert sum(c.issue for c in cases) >= 40  # every case the issue lists
    for c in cases:
        assert (c.code is None) != (c.argv is None), c.id
        assert c.prelude in ("x64", "x32", "none"), c.id


def test_two_cases_through_the_command_line(tmp_path):
    """A library refusal and a command line's refusal against this checkout: both GOOD, and the
    summary's schema (per case: category, outcome, seconds, evidence; totals per category)."""
    out = tmp_path / "out"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "tests.probe",
            "--tree",
            str(ROOT),
            "--out",
            str(out),
            "--only",
            "random-smooth-integer-key,sweep-spec-dev-zero",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["complete"] and s["totals"]["cases"] == 2
    assert set(s["results"]) == {"random-smooth-integer-key", "sweep-spec-dev-zero"}
    for rec in s["results"].values():
        assert rec["outcome"] == "GOOD", rec
        assert {"category", "outcome", "seconds", "cpu_seconds", "evidence", "issue", "description"} <= set(rec)
    assert s["totals"]["by_outcome"] == {"GOOD": 2, "POOR": 0, "BAD": 0}
    assert s["totals"]["by_category"] == {
        "late_or_unclear": {"GOOD": 1, "POOR": 0, "BAD": 0},
        "files": {"GOOD": 1, "POOR": 0, "BAD": 0},
    }
    table = (out / "cases.md").read_text()
    assert "| late_or_unclear | 1 | 0 | 0 |" in table and "sweep-spec-dev-zero" in table
