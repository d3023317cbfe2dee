"""A user's files: devices, pipes, links, directories and large files where a small regular file is
expected; encodings, line endings and malformed rows of samples files; hand-made gains files."""

from __future__ import annotations

import json
import re

from tests.probe import specs
from tests.probe.harness import BAD, GOOD, POOR, Case
from tests.probe.oracles import answer, cli_refuses, hang, refuses, short

CAT = "files"
NOT_REGULAR = r"regular file|not a file|directory|device|/dev/zero|larger than|too large|MiB"


LOAD = 'arm()\nref = R.load_samples("FILE")\nemit(position_at_1s=[float(v) for v in ref.position(1.0)])\n'


def _load(cid, desc, name, pattern, files=None, setup="", issue=False, timeout=60, accepted=BAD, wall=None) -> Case:
    return Case(
        f"load-samples-{cid}",
        CAT,
        desc,
        refuses(pattern, accepted=accepted),
        code=setup + LOAD.replace("FILE", name),
        files=files or {},
        issue=issue,
        timeout=timeout,
        wall=wall,
    )


CIRCLE = specs.circle_csv(0.0, 4.0, 81)
SAME = """
plain = R.load_samples("plain.csv")
arm()
ref = R.load_samples("s.csv")
ts = jnp.linspace(0.0, 4.0, 41)
d = float(jnp.max(jnp.abs(jax.vmap(ref.position)(ts) - jax.vmap(plain.position)(ts))))
emit(difference=d)
"""


_BIG = "import os\nwith open('big.csv', 'wb') as f:\n    f.write(b't,x,y\\n')\n    f.truncate(100 * 2**20)\n"
_ROWS = CIRCLE.splitlines()


def _with_row(i: int, text: str) -> str:
    """The circle's CSV with row ``i`` replaced."""
    return "\n".join(_ROWS[:i] + [text] + _ROWS[i + 1 :]) + "\n"


def _same_path(r):
    """The path read from the file against the plain file's: (equal, evidence)."""
    return r["difference"] == 0.0, f"loaded; the path differs from the plain file's by {r['difference']:.3g}"


LIBRARY = [
    _load("dev-zero", "references.load_samples('/dev/zero')", "/dev/zero", NOT_REGULAR, issue=True),
    _load(
        "fifo",
        "load_samples of a named pipe nobody writes to",
        "s.csv",
        NOT_REGULAR,
        setup="import os\nos.mkfifo('s.csv')\n",
        wall=60,
    ),
    _load(
        "symlink-to-dev-zero",
        "load_samples of a link to /dev/zero",
        "s.csv",
        NOT_REGULAR,
        setup="import os\nos.symlink('/dev/zero', 's.csv')\n",
    ),
    _load("directory", "load_samples of a directory", "s.csv", NOT_REGULAR, setup="import os\nos.mkdir('s.csv')\n"),
    _load(
        "sparse-100MiB",
        "load_samples of a 100 MiB file (a header and NUL bytes)",
        "big.csv",
        NOT_REGULAR + r"|big\.csv",
        setup=_BIG,
    ),
    _load("utf16", "load_samples of a UTF-16 CSV", "s.csv", r"s\.csv", files={"s.csv": CIRCLE.encode("utf-16")}),
    _load(
        "latin1-comment",
        "load_samples of a CSV with a Latin-1 byte in a comment line",
        "s.csv",
        r"s\.csv",
        files={"s.csv": b"# r\xe9sum\xe9\n" + CIRCLE.encode()},
    ),
    _load(
        "decimal-comma",
        "load_samples of a CSV with one value written 1,5 (a ragged row)",
        "s.csv",
        r"s\.csv|row|line|column",
        files={"s.csv": _with_row(10, "0.45,1,5,0.45")},
    ),
    _load(
        "nan-value",
        "load_samples of a CSV with a nan position",
        "s.csv",
        r"finite|nan",
        files={"s.csv": _with_row(10, "0.45,nan,0.45")},
    ),
    _load(
        "text-value",
        "load_samples of a CSV with the value 'abc'",
        "s.csv",
        r"s\.csv|abc",
        files={"s.csv": _with_row(10, "0.45,abc,0.45")},
    ),
    _load("empty", "load_samples of an empty file", "s.csv", r"s\.csv|empty|header|column", files={"s.csv": ""}),
    _load(
        "header-only",
        "load_samples of a CSV with a header and no rows",
        "s.csv",
        r"sample|row|s\.csv",
        files={"s.csv": "t,x,y\n"},
    ),
    _load(
        "tab-separated",
        "load_samples of a tab-separated file",
        "s.csv",
        r"column|s\.csv",
        files={"s.csv": CIRCLE.replace(",", "\t")},
    ),
    Case(
        "load-samples-byte-order-mark",
        CAT,
        "load_samples of a CSV starting with a UTF-8 byte-order mark (control: the same path as without)",
        answer(_same_path),
        code=SAME,
        files={"plain.csv": CIRCLE, "s.csv": b"\xef\xbb\xbf" + CIRCLE.encode()},
    ),
    Case(
        "load-samples-crlf",
        CAT,
        "load_samples of a CSV with CRLF line endings (control: the same path)",
        answer(_same_path),
        code=SAME,
        files={"plain.csv": CIRCLE, "s.csv": CIRCLE.replace("\n", "\r\n").encode()},
    ),
]


DRIVE = """
import os
from probe_driver import run
SETUP
r = run(*ARGV, timeout=TIMEOUT)
emit(run=r)
"""


def _driven(pattern: str, accepted=BAD):
    """A command line run by a driver (its input made first): like cli_refuses, from the driver's facts."""

    def oracle(run):
        if run.timed_out:
            return hang(run)
        r = run.results["run"]
        if r["rc"] is None:
            return BAD, f"no answer after {r['seconds']:.0f} s (killed): {short(r['last'])}"
        if r["rc"] == 0:
            return accepted, f"exit 0 (accepted): {short(r['last'])}"
        if r["traceback"] or r["rc"] not in (1, 2):
            return POOR, f"exit {r['rc']} with a raw traceback: {short(r['last'])}"
        if re.search(pattern, r["last"], re.I):
            return GOOD, f"exit {r['rc']}: {short(r['last'])}"
        return POOR, f"exit {r['rc']}, message not naming the cause: {short(r['last'])}"

    return oracle


def _drive(cid, desc, argv, setup, pattern, files=None, issue=False, timeout=90) -> Case:
    code = DRIVE.replace("SETUP", setup).replace("*ARGV", f"*{tuple(argv)!r}").replace("TIMEOUT", str(timeout))
    return Case(
        cid,
        CAT,
        desc,
        _driven(pattern),
        code=code,
        files=files or {},
        prelude="none",
        issue=issue,
        timeout=timeout + 30,
        wall=timeout + 40,
    )


def _ran_ok(run):
    if run.timed_out:
        return hang(run, POOR)
    if run.rc == 0:
        return GOOD, f"exit 0: {short((run.stdout.strip().splitlines() or [''])[-1])}"
    m = [x for x in run.stderr.splitlines() if "error" in x]
    return POOR, f"a valid file refused (exit {run.rc}): {short(m[-1] if m else run.last_line)}"


def _gains_spec(name: str) -> dict:
    return {"s.toml": specs.sweep(1.0, [("poles = 1.0", f'file = "{name}"')])}


_SWEEP = ("-m", "wmrjax", "sweep", "s.toml", "--out", "out")
_SAMPLES = specs.SAMPLES_SWEEP.replace("T_FINAL", "2.0")
_CERTIFY = ("-m", "wmrjax", "certify", "--t-final", "10", *specs.CERTIFY_SMALL, "--out", "out")
_GOOD_GAINS = json.loads(specs.gains_json("(2,0)", "velocity", "dynamic", [[1.0, 2.0], [1.0, 2.0]]))
_NAN_GAINS = json.dumps(_GOOD_GAINS).replace("[1.0, 2.0]", "[NaN, 2.0]", 1)


def _edit(**kw) -> str:
    """The good gains file with some keys replaced."""
    return json.dumps({**_GOOD_GAINS, **kw})


CLI = [
    Case(
        "sweep-reference-file-dev-zero",
        CAT,
        '[reference] file = "/dev/zero" in a sweep file',
        cli_refuses(NOT_REGULAR),
        argv=_SWEEP,
        files={"s.toml": _SAMPLES.replace("circle.csv", "/dev/zero")},
        issue=True,
    ),
    Case(
        "sweep-gains-file-dev-zero",
        CAT,
        '[gains] file = "/dev/zero" in a sweep file',
        cli_refuses(NOT_REGULAR),
        argv=_SWEEP,
        files=_gains_spec("/dev/zero"),
        issue=True,
    ),
    Case(
        "sweep-gains-option-dev-zero",
        CAT,
        "wmrjax sweep --compare-gains /dev/zero",
        cli_refuses(NOT_REGULAR),
        argv=(*_SWEEP, "--compare-gains", "/dev/zero"),
        files={"s.toml": specs.sweep(1.0)},
    ),
    Case(
        "tuning-reference-dev-zero",
        CAT,
        "wmrjax tune --reference /dev/zero",
        cli_refuses(NOT_REGULAR),
        argv=("-m", "wmrjax", "tune", "--reference", "/dev/zero", *specs.TUNE_SMALL, "--out", "out"),
    ),
    Case(
        "tuning-problem-dev-zero",
        CAT,
        "wmrjax tune /dev/zero (the problem file)",
        cli_refuses(NOT_REGULAR),
        argv=("-m", "wmrjax", "tune", "/dev/zero", "--out", "out"),
    ),
    Case(
        "certify-problem-dev-zero",
        CAT,
        "wmrjax certify /dev/zero (the problem file)",
        cli_refuses(NOT_REGULAR),
        argv=("-m", "wmrjax", "certify", "/dev/zero", "--out", "out"),
    ),
    Case(
        "certify-gains-dev-zero",
        CAT,
        "wmrjax certify --gains /dev/zero",
        cli_refuses(NOT_REGULAR),
        argv=(*_CERTIFY, "--gains", "/dev/zero"),
    ),
    Case(
        "sweep-spec-dev-zero",
        CAT,
        "wmrjax sweep /dev/zero (the sweep file)",
        cli_refuses(NOT_REGULAR + "|not found"),
        argv=("-m", "wmrjax", "sweep", "/dev/zero", "--out", "out"),
    ),
    _drive(
        "sweep-gains-file-fifo",
        "[gains] file = a named pipe nobody writes to, in a sweep file",
        _SWEEP,
        "os.mkfifo('g.json')",
        NOT_REGULAR + r"|g\.json",
        files=_gains_spec("g.json"),
    ),
    _drive(
        "sweep-reference-file-fifo",
        "[reference] file = a named pipe nobody writes to, in a sweep file",
        _SWEEP,
        "os.mkfifo('circle.csv')",
        NOT_REGULAR + r"|circle\.csv",
        files={"s.toml": _SAMPLES},
    ),
    _drive(
        "sweep-spec-directory",
        "wmrjax sweep DIR (a directory as the sweep file)",
        ("-m", "wmrjax", "sweep", "s.toml", "--out", "out"),
        "os.mkdir('s.toml')",
        r"s\.toml",
    ),
    _drive(
        "sweep-gains-file-directory",
        '[gains] file = "g.json", a directory',
        _SWEEP,
        "os.mkdir('g.json')",
        NOT_REGULAR + r"|g\.json",
        files=_gains_spec("g.json"),
    ),
    Case(
        "sweep-gains-file-truncated",
        CAT,
        "[gains] file = a gains.json cut in half",
        cli_refuses(r"g\.json"),
        argv=_SWEEP,
        files={**_gains_spec("g.json"), "g.json": _edit()[:60]},
    ),
    Case(
        "sweep-gains-file-nan",
        CAT,
        "[gains] file = a gains.json with a NaN coefficient",
        cli_refuses(r"finite|nan|g\.json"),
        argv=_SWEEP,
        files={**_gains_spec("g.json"), "g.json": _NAN_GAINS},
    ),
    Case(
        "sweep-gains-file-not-hurwitz",
        CAT,
        "[gains] file = a gains.json with coefficients [-1, 2] (unstable)",
        cli_refuses(r"Hurwitz|unstable|converge"),
        argv=_SWEEP,
        files={**_gains_spec("g.json"), "g.json": _edit(coefficients=[[-1.0, 2.0], [1.0, 2.0]])},
    ),
    Case(
        "sweep-gains-file-wrong-kind",
        CAT,
        '[gains] file = a JSON file with kind = "something else"',
        cli_refuses(r"g\.json|kind"),
        argv=_SWEEP,
        files={**_gains_spec("g.json"), "g.json": _edit(kind="something else")},
    ),
    Case(
        "sweep-reference-file-utf16",
        CAT,
        "[reference] file = a UTF-16 CSV in a sweep file",
        cli_refuses(r"circle\.csv"),
        argv=_SWEEP,
        files={"s.toml": _SAMPLES, "circle.csv": CIRCLE.encode("utf-16")},
    ),
    Case(
        "sweep-reference-file-bom",
        CAT,
        "[reference] file = a CSV with a byte-order mark (control: runs)",
        _ran_ok,
        argv=_SWEEP,
        files={"s.toml": _SAMPLES, "circle.csv": b"\xef\xbb\xbf" + CIRCLE.encode()},
        timeout=150,
    ),
]


def cases() -> list[Case]:
    """Every files case."""
    return LIBRARY + CLI
