"""Outside what the user named (issue 57): writes outside ``--out``, deletions of files a job did
not write, code run from the user's files, two jobs' results in one directory, orphaned
workers, sizes allocated before they are estimated, an exported step used past its path, and
messages that quote a file at length."""

from __future__ import annotations

from tests.probe import specs
from tests.probe.harness import BAD, Case
from tests.probe.oracles import answer, cli_refuses, refuses

CAT = "outputs"

# every file under the case's directory but the drivers' logs, as relative paths
LISTING = """
import os
def listing(root="."):
    found = set()
    for d, _, names in os.walk(root):
        for n in names:
            p = os.path.relpath(os.path.join(d, n), root)
            if not (d == root and n.startswith(".p")):
                found.add(p)
    return found
"""

ESCAPING_CASE = (
    LISTING
    + """
from probe_driver import run
before = listing()
r = run("-m", "wmrjax", "sweep", "s.toml", "--out", "a/b/c/out")
outside = sorted(p for p in listing() - before if not p.startswith("a/b/c/out/"))
emit(rc=r["rc"], last=r["last"], outside=outside)
"""
)


def _nothing_outside(r):
    ok = not r["outside"]
    return ok, f"exit {r['rc']}: {r['last'][:160]}; written outside --out: {r['outside'][:5]}"


EXPORT_LINKS = """
import os
from probe_driver import run
ref = run("-m", "wmrjax", "export", "s.toml", "--out", "ref")
names = [n for n in os.listdir("ref") if not n.startswith(".")]
os.makedirs("out")
for n in names:
    with open("target_" + n, "w") as f:
        f.write("the user's")
    os.symlink(os.path.abspath("target_" + n), os.path.join("out", n))
again = run("-m", "wmrjax", "export", "s.toml", "--out", "out")
changed = [n for n in names if open("target_" + n).read() != "the user's"]
emit(ref=ref["rc"], rc=again["rc"], names=names, changed=changed, last=again["last"])
"""


def _links_kept(r):
    ok = r["ref"] == 0 and r["rc"] == 0 and not r["changed"]
    return ok, f"export exit {r['rc']} over links named {r['names'][:4]}; targets written through: {r['changed']}"


USER_TMP = """
import os
from probe_driver import run
os.makedirs("mydata/deep")
for p in ("mydata/.x.tmp", "mydata/deep/.report.tmp", "mydata/deep/notes.txt"):
    with open(p, "w") as f:
        f.write("mine")
r = run("-m", "wmrjax", "sweep", "s.toml", "--out", "mydata")
kept = [p for p in ("mydata/.x.tmp", "mydata/deep/.report.tmp", "mydata/deep/notes.txt") if os.path.exists(p)]
emit(rc=r["rc"], kept=kept, last=r["last"])
"""


def _user_files_kept(r):
    return len(r["kept"]) == 3 and r["rc"] == 0, f"sweep exit {r['rc']}; the user's files left: {r['kept']}"


PLANTED = """
import os
from probe_driver import run
os.makedirs("out")
for name in ("json.py", "numpy.py", "os.py"):
    with open(os.path.join("out", name), "w") as f:
        f.write("open(%r, 'w').write('ran')\\n" % os.path.abspath("RAN_" + name))
r = run("-m", "wmrjax", "export", "s.toml", "--out", "out")
ran = sorted(n for n in os.listdir(".") if n.startswith("RAN_"))
emit(rc=r["rc"], ran=ran, last=r["last"])
"""


def _nothing_ran(r):
    return r["rc"] == 0 and not r["ran"], f"export exit {r['rc']}; the user's modules run: {r['ran']}"


OTHER_JOB = """
import os
from probe_driver import run, read_json
first = run(*FIRST, "--out", "out")
with open("out/notes.md", "w") as f:
    f.write("mine")
os.symlink("out", "link")
before = read_json("out/summary.json") or {}
second = run(*SECOND, "--out", TARGET)
after = read_json("out/summary.json") or {}
facts = dict(first=first["rc"], second=second["rc"], last=second["last"],
             same_summary=before == after, experiment=after.get("experiment"))
fresh = run(*SECOND, "--out", TARGET, "--fresh")
files = sorted(n for n in os.listdir("out") if not n.startswith("."))
emit(fresh=fresh["rc"], fresh_last=fresh["last"], files=files, notes=os.path.exists("out/notes.md"), **facts)
"""


def _one_job(first_files, second_files):
    def check(r):
        refused = r["first"] == 0 and r["second"] != 0 and r["same_summary"] and "--fresh" in r["last"]
        left = set(r["files"]) - {"notes.md"}
        replaced = r["fresh"] == 0 and r["notes"] and not (left & set(first_files)) and set(second_files) <= left
        return refused and replaced, (
            f"into another job's --out: exit {r['second']} ({r['last'][:120]}), its summary kept: "
            f"{r['same_summary']}; with --fresh: exit {r['fresh']}, files {r['files'][:8]}, the user's kept: {r['notes']}"
        )

    return check


def _other_job(first: tuple, second: tuple, target: str) -> str:
    return f"FIRST = {first!r}\nSECOND = {second!r}\nTARGET = {target!r}\n" + OTHER_JOB


SWEEP = ("-m", "wmrjax", "sweep", "s.toml")
CERTIFY = ("-m", "wmrjax", "certify", "s.toml", *specs.CERTIFY_SMALL)

ORPHANS = """
import os, time
from probe_driver import start, wait_for, children, kill9
p = start("-m", "wmrjax", "sweep", "slow.toml", "--out", "out", "--processes", "2", "--devices", "1")
workers = []
for _ in range(600):
    workers = children(p.pid)
    if len(workers) >= 2:
        break
    time.sleep(0.1)
time.sleep(3.0)
kill9(p.pid)
p.finish(60)
time.sleep(5.0)
alive = [w for w in workers if os.path.exists(f"/proc/{w}") and "Z" not in open(f"/proc/{w}/stat").read().split()[2]]
for w in alive:
    kill9(w)
emit(workers=len(workers), alive=len(alive))
"""


def _no_orphans(r):
    return r["workers"] >= 2 and r[
        "alive"
    ] == 0, f"{r['workers']} workers, {r['alive']} still running 5 s after the launcher's kill -9"


PAST_SPAN = """
import os, json
from probe_driver import run
r = run("-m", "wmrjax", "export", "p.toml", "--out", "out")
summary = json.load(open("out/summary.json")) if r["rc"] == 0 else {}
headers = [open(os.path.join("out", n)).read() for n in os.listdir("out") if n.endswith(".h")]
emit(rc=r["rc"], keys=sorted(summary)[:40],
     header_says=any("span" in h.lower() or "valid" in h.lower() for h in headers), last=r["last"])
"""


def _span_stated(r):
    ok = r["rc"] == 0 and r["header_says"] and any("span" in k for k in r["keys"])
    return (
        ok,
        f"export exit {r['rc']}; the header states the span: {r['header_says']}; summary keys with 'span': {[k for k in r['keys'] if 'span' in k]}",
    )


SAMPLED = """[controller]
law = "dynamic"
robot = "(2,0)"
[geometry]
e = 0.3
[reference]
family = "samples"
file = "path.csv"
[initial]
space = "output"
x = [0.0, 0.1]
[simulation]
t_final = 4.0
dt = 0.02
"""


# one reference (the small sweep's two radii made one), 10 steps: what an export and a
# certification take
EXPORTABLE = specs.sweep(
    changes=[
        ("options = { radius = [2.0, 3.0], omega = 0.5 }", "options = { radius = 2.0, omega = 0.5 }"),
        ("t_final = 2.0", "t_final = 0.2"),
    ]
)


def _case_file(name: str) -> str:
    return specs.sweep(changes=[("t_final = 2.0", "t_final = 0.2")]) + f'[[case]]\nname = "{name}"\n'


def _driver(cid: str, description: str, check, code: str, files: dict, timeout: float = 400) -> Case:
    """A case that starts the tree's processes itself (``code``, no prelude) and whose facts
    ``check(results) -> (ok, evidence)`` judges: GOOD when it holds, BAD when not."""
    return Case(cid, CAT, description, answer(check), code=code, files=files, prelude="none", timeout=timeout)


def cases() -> list[Case]:
    """This module's cases."""
    return [
        _driver(
            "case-name-escapes-out",
            'a sweep whose [[case]] name is "../../../X/Y" (before: a PNG written outside --out, exit 0)',
            _nothing_outside,
            ESCAPING_CASE,
            {"s.toml": _case_file("../../../X/Y")},
            timeout=240,
        ),
        _driver(
            "export-through-links",
            "export into an --out whose output files are links to the user's files (before: written through)",
            _links_kept,
            EXPORT_LINKS,
            {"s.toml": EXPORTABLE},
            timeout=400,
        ),
        _driver(
            "user-tmp-files-kept",
            "a sweep into --out mydata holding the user's .x.tmp and deep/.report.tmp (before: deleted)",
            _user_files_kept,
            USER_TMP,
            {"s.toml": specs.sweep()},
            timeout=240,
        ),
        _driver(
            "export-runs-no-user-module",
            "export into an --out holding json.py, numpy.py, os.py (before: json.py imported and run)",
            _nothing_ran,
            PLANTED,
            {"s.toml": EXPORTABLE},
            timeout=400,
        ),
        _driver(
            "certify-into-a-sweeps-out",
            "certify into a finished sweep's --out, then with --fresh (before: both exit 0, summaries mixed)",
            _one_job(["runs.parquet"], ["summary.json", "slice_map.png"]),
            _other_job(SWEEP, CERTIFY, "out"),
            {"s.toml": EXPORTABLE},
            timeout=400,
        ),
        _driver(
            "certify-into-a-sweeps-out-by-link",
            "certify into a link to a finished sweep's --out, then with --fresh",
            _one_job(["runs.parquet"], ["summary.json", "slice_map.png"]),
            _other_job(SWEEP, CERTIFY, "link"),
            {"s.toml": EXPORTABLE},
            timeout=400,
        ),
        _driver(
            "sweep-into-a-certifications-out",
            "a sweep into a finished certification's --out, then with --fresh",
            _one_job(["slice_map.png"], ["summary.json", "runs.parquet"]),
            _other_job(CERTIFY, SWEEP, "out"),
            {"s.toml": EXPORTABLE},
            timeout=400,
        ),
        _driver(
            "killed-launcher-workers",
            "kill -9 of the launcher of sweep --processes 2 (before: its workers ran on and overwrote the next run)",
            _no_orphans,
            ORPHANS,
            {"slow.toml": specs.SLOW_SWEEP},
            timeout=300,
        ),
        _driver(
            "export-states-its-span",
            "export of a sampled path: the valid time span in the C header and summary.json (before: in neither)",
            _span_stated,
            PAST_SPAN,
            {"p.toml": SAMPLED, "path.csv": specs.circle_csv(0.0, 4.0, 81)},
            timeout=400,
        ),
        Case(
            "export-initial-99",
            CAT,
            "wmrjax export --initial 99 on a problem of 9 initial states (before: parsed and ignored)",
            cli_refuses(r"initial|99"),
            argv=("-m", "wmrjax", "export", "s.toml", "--initial", "99"),
            files={"s.toml": EXPORTABLE},
        ),
        Case(
            "random-count-1e9",
            CAT,
            "[initial] random = { count = 1e9 } (before: 7.45 GiB allocated before any estimate)",
            cli_refuses(r"count|GB|memory"),
            argv=("-m", "wmrjax", "sweep", "s.toml"),
            files={
                "s.toml": specs.sweep(
                    changes=[
                        (
                            "x = [-0.5, 0.0, 0.7]\ny = { min = -1.0, max = 1.0, num = 3 }",
                            "random = { count = 1000000000, seed = 0 }\nx = { low = -0.5, high = 0.5 }",
                        )
                    ]
                )
            },
        ),
        Case(
            "grid-num-1e9",
            CAT,
            "a grid with num = 1e9 (before: allocated before any estimate)",
            cli_refuses(r"num|GB|memory"),
            argv=("-m", "wmrjax", "sweep", "s.toml"),
            files={"s.toml": specs.sweep(changes=[("num = 3", "num = 1000000000")])},
        ),
        Case(
            "knots-1e6",
            CAT,
            "[tune.family] knots = 1e6 (before: compiled without end)",
            cli_refuses(r"knots"),
            argv=("-m", "wmrjax", "tune", "t.toml", "--set", "tune.family.knots=1000000"),
            files={"t.toml": specs.TUNE},
        ),
        Case(
            "samples-1e6-rows",
            CAT,
            "load_samples of 10^6 rows (before: a raw RESOURCE_EXHAUSTED after minutes)",
            refuses(r"GB|memory|resample|rows|samples"),
            code=HUGE.replace("N_ROWS", "1000000"),
            timeout=120,
        ),
        Case(
            "samples-1e5-rows",
            CAT,
            "load_samples of 10^5 rows (before: 63 s and 1.9 GB at 10^4): loads, its position right",
            answer(_huge_loaded),
            code=HUGE.replace("N_ROWS", "100000"),
            timeout=120,
        ),
        Case(
            "samples-environ",
            CAT,
            "a samples file named /proc/self/environ (before: the whole environment on stderr)",
            refuses(r"environ|not a text file|NUL|regular", accepted=BAD),
            code='import os\nos.environ["PROBE_SECRET"] = "s3cr3t-value"\narm()\nR.load_samples("/proc/self/environ")\n',
        ),
        Case(
            "samples-5MB-header",
            CAT,
            "a samples file whose header line is 5 MB (before: a 5 MB message)",
            answer(_short_message),
            code='open("h.csv", "w").write("t,x,y" + ",z" * 2_500_000 + "\\n0,0,0\\n1,1,1\\n")\n'
            "try:\n    R.load_samples('h.csv')\n    emit(length=None)\n"
            "except ValueError as exc:\n    emit(length=len(str(exc)), secret=False)\n",
        ),
    ]


HUGE = """
import numpy as np, time
n = N_ROWS
t = np.linspace(0.0, n * 0.01, n)
np.savetxt("big.csv", np.stack([t, 2 * np.cos(0.01 * t), 2 * np.sin(0.01 * t)], 1), delimiter=",", header="t,x,y", comments="")
arm()
t0 = time.monotonic()
ref = R.load_samples("big.csv")
p = [float(v) for v in ref.position(0.5 * n * 0.01)]
emit(seconds=time.monotonic() - t0, position=p, expected=[2 * np.cos(0.005 * n * 0.01), 2 * np.sin(0.005 * n * 0.01)])
"""


def _huge_loaded(r):
    err = max(abs(a - b) for a, b in zip(r["position"], r["expected"]))
    return err < 1e-6, f"loaded in {r['seconds']:.1f} s; position off by {err:.2g} m"


def _short_message(r):
    n = r["length"]
    return n is not None and n < 1000, f"refused with a message of {n} characters"
