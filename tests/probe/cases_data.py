"""Data loss and mixed results: concurrent writers, foreign, torn and moved blocks, stale
temporary files, corrupt state files, killed and resumed runs, hand-edited checkpoints."""

from __future__ import annotations

import re

from tests.probe import specs
from tests.probe.harness import BAD, GOOD, POOR, Case
from tests.probe.oracles import hang, refuses, short

CAT = "data_loss"
WRITER = r"another (run|process|writer|sweep)|being written|lock|process \d+"


# --- two writers into one --out (real concurrent processes) ------------------------------------

TWO_WRITERS = """
from probe_driver import start, run, same_output
a = start(*A, "--out", "out")
b = start(*B, "--out", "out")
ra, rb = a.finish(400), b.finish(400)
facts = dict(a=ra, b=rb)
for name, argv, kind, r in (("a", A, KIND_A, ra), ("b", B, KIND_B, rb)):
    if r["rc"] == 0:
        run(*argv, "--out", "ref_" + name)
        facts["is_" + name] = same_output("out", "ref_" + name, kind)
emit(**facts)
"""


def _two_writers(a: tuple, b: tuple, kind_a: str, kind_b: str) -> str:
    return f"A = {a!r}\nB = {b!r}\nKIND_A = {kind_a!r}\nKIND_B = {kind_b!r}\n" + TWO_WRITERS


def _two_writers_oracle(run):
    """One writer refused naming the other, the output the survivor's alone: GOOD; both exit 0
    (one run's results lost or mixed) or a survivor whose output is not its own: BAD."""
    if run.timed_out:
        return hang(run)
    r = run.results
    a, b = r["a"], r["b"]
    ok = [n for n, x in (("a", a), ("b", b)) if x["rc"] == 0]
    if len(ok) == 2:
        return BAD, (
            f"both exit 0 into one --out; its outputs equal a's run alone: {r.get('is_a')}, b's: {r.get('is_b')}"
        )
    if not ok:
        return POOR, f"both failed: a {a['rc']} ({short(a['last'])}), b {b['rc']} ({short(b['last'])})"
    win, lose = ok[0], ("b" if ok[0] == "a" else "a")
    loser = r[lose]
    if not r.get("is_" + win):
        return BAD, f"{lose} refused, but the outputs are not {win}'s run alone"
    if loser["traceback"] or not re.search(WRITER, loser["last"], re.I):
        return POOR, f"{lose} failed unclearly (exit {loser['rc']}): {short(loser['last'])}"
    return GOOD, f"{lose} refused (exit {loser['rc']}): {short(loser['last'])}; the outputs are {win}'s alone"


SWEEP_A = ("-m", "wmrjax", "sweep", "a.toml")
SWEEP_B = ("-m", "wmrjax", "sweep", "b.toml")
SWEEP_FILES = {"a.toml": specs.sweep(1.0), "b.toml": specs.sweep(2.0)}


def _concurrency() -> list[Case]:
    tune0 = ("-m", "wmrjax", "tune", "tune.toml", "--set", "tune.seed=0")
    tune1 = ("-m", "wmrjax", "tune", "tune.toml", "--set", "tune.seed=1")
    both = {"a.toml": specs.sweep(1.0), "tune.toml": specs.TUNE}
    return [
        Case(
            "two-sweeps-one-out",
            CAT,
            "two different sweeps (poles 1 and 2) started together into one --out",
            _two_writers_oracle,
            code=_two_writers(SWEEP_A, SWEEP_B, "sweep", "sweep"),
            files=SWEEP_FILES,
            prelude="none",
            timeout=240,
            issue=True,
        ),
        Case(
            "two-tunings-one-out",
            CAT,
            "two tunings (--set tune.seed=0 and tune.seed=1) started together into one --out",
            _two_writers_oracle,
            code=_two_writers(tune0, tune1, "tune", "tune"),
            files={"tune.toml": specs.TUNE},
            prelude="none",
            timeout=240,
            issue=True,
        ),
        Case(
            "sweep-and-tuning-one-out",
            CAT,
            "a sweep and a tuning (both write summary.json) started together into one --out",
            _two_writers_oracle,
            code=_two_writers(SWEEP_A, ("-m", "wmrjax", "tune", "tune.toml"), "sweep", "tune"),
            files=both,
            prelude="none",
            timeout=240,
        ),
    ]


# --- a finished sweep's directory tampered with, then the same sweep run again ------------------

RERUN = """
import os, shutil
from probe_driver import run, same_table, rows, read_json, finished
first = finished("a.toml", "out")
shutil.copy("out/runs.parquet", "original.parquet")
block = lambda b: "out/blocks/block_%06d.npz" % b
TAMPER
again = run("-m", "wmrjax", "sweep", "a.toml", *EXTRA, "--out", "out")
left = sorted(os.path.join(d, f) for d, _, fs in os.walk("out") for f in fs if f.endswith(".wmrjax-tmp"))
emit(first=first, again=again, same=same_table("out/runs.parquet", "original.parquet"),
     rows=rows("out/runs.parquet"), left=left)
"""


def _rerun(tamper: str, extra: tuple = ()) -> str:
    return RERUN.replace("TAMPER", tamper).replace("*EXTRA", f"*{extra!r}")


def _rerun_oracle(named: str, leftovers: bool = False):
    """After tampering, the rerun exits 0 with the original table (recomputed) -- GOOD -- or is
    refused naming the file (``named``) -- GOOD; exit 0 with another table is BAD (foreign or
    torn data in the results); a raw traceback is POOR. With ``leftovers``, temporary files
    a killed write left must be gone after the rerun (POOR otherwise: litter, not loss)."""

    def oracle(run):
        if run.timed_out:
            return hang(run)
        r = run.results
        again = r["again"]
        if r["first"]["rc"] != 0:
            return POOR, f"the first run failed: {short(r['first']['last'])}"
        if again["rc"] == 0:
            if not r["same"]:
                return BAD, f"exit 0 with a different table ({r['rows']} rows): foreign or torn data assembled"
            if leftovers and r["left"]:
                return POOR, f"same table, but the killed write's temporary files are still there: {r['left']}"
            said = re.findall(named, again["err"], re.I)
            return GOOD, "exit 0, the original table" + (f"; named on stderr: {said[0]}" if said else "")
        if again["traceback"] or again["rc"] not in (1, 2):
            return POOR, f"exit {again['rc']} with a raw traceback: {short(again['last'])}"
        if re.search(named, again["last"], re.I):
            return GOOD, f"refused (exit {again['rc']}): {short(again['last'])}"
        return POOR, f"refused without naming the file (exit {again['rc']}): {short(again['last'])}"

    return oracle


_FOREIGN = 'finished("b.toml", "other")\nshutil.copy("other/blocks/block_000000.npz", block(0))'
_TORN = "data = open(block(2), 'rb').read()\nopen(block(2), 'wb').write(data[: len(data) // 2])"
_BLOCK_TAMPERS = [
    ("foreign-block", "a block file of another sweep (poles 2) copied into blocks/", _FOREIGN, True),
    ("torn-block", "a block file truncated to half its length (a torn write)", _TORN, True),
    ("moved-block", "block 3's file copied over block 1's", "shutil.copy(block(3), block(1))", False),
    ("empty-block", "a block file of 0 bytes", "open(block(1), 'wb').close()", False),
    ("garbage-block", "a block file of bytes that are not a zip file", "open(block(1), 'wb').write(b'x' * 500)", False),
    ("block-is-directory", "a block file replaced by a directory", "os.remove(block(1)); os.mkdir(block(1))", False),
    ("extra-block", "a copy of block 0 as block 99 (beyond the plan)", "shutil.copy(block(0), block(99))", False),
    (
        "table-deleted",
        "runs.parquet deleted, the blocks kept (control: reassembled)",
        "os.remove('out/runs.parquet')",
        False,
    ),
]


_STATE_TAMPERS = [
    (
        "corrupt-state",
        "sweep_state.json overwritten with '{not json'",
        "open('out/sweep_state.json', 'w').write('{not json')",
    ),
    (
        "state-is-directory",
        "sweep_state.json replaced by a directory",
        "os.remove('out/sweep_state.json'); os.mkdir('out/sweep_state.json')",
    ),
    (
        "state-of-other-sweep",
        "sweep_state.json of another sweep (poles 2) copied in",
        'finished("b.toml", "other")\nshutil.copy("other/sweep_state.json", "out/sweep_state.json")',
    ),
]


def _blocks() -> list[Case]:
    out = []
    for cid, desc, tamper, issue in _BLOCK_TAMPERS:
        out.append(
            Case(
                f"sweep-{cid}",
                CAT,
                f"{desc}, then the same sweep run again",
                _rerun_oracle(r"block_0000\d\d\.npz|block \d+"),
                code=_rerun(tamper),
                files=SWEEP_FILES,
                prelude="none",
                timeout=180,
                issue=issue,
            )
        )
    for cid, desc, tamper in _STATE_TAMPERS:
        out.append(
            Case(
                f"sweep-{cid}",
                CAT,
                f"{desc}, then the same sweep run again",
                _rerun_oracle(r"sweep_state\.json|another sweep|--fresh"),
                code=_rerun(tamper),
                files=SWEEP_FILES,
                prelude="none",
                timeout=180,
            )
        )
    tmp = "open('out/.runs.parquet.x1.wmrjax-tmp', 'wb').write(b'half')\nopen('out/blocks/.block_000000.npz.x2.wmrjax-tmp', 'wb').write(b'half')"
    out.append(
        Case(
            "sweep-stale-tmp-files",
            CAT,
            "the temporary files a kill -9 during the table and a block write leaves, then the sweep run again",
            _rerun_oracle(r"tmp|temporary", leftovers=True),
            code=_rerun(tmp),
            files=SWEEP_FILES,
            prelude="none",
            timeout=180,
            issue=True,
            note="the kill is simulated by writing the files a killed atomic write leaves ('.NAME.*.wmrjax-tmp'); "
            "a leftover is POOR (litter), not data loss",
        )
    )
    return out


# --- killed and resumed runs ------------------------------------------------------------------

KILLED = """
import os
from probe_driver import start, run, wait_for, kill9, same_output, rows, finished
p = start("-m", "wmrjax", "sweep", "slow.toml", "--out", "out")
started = wait_for("out/blocks/block_000001.npz", 240)
kill9(p.pid)
p.finish()
done = len([f for f in os.listdir("out/blocks") if f.endswith(".npz")]) if started else 0
again = run("-m", "wmrjax", "sweep", "RESUME", "--out", "out")
finished("RESUME", "ref")
emit(started=started, blocks_at_kill=done, again=again, same=same_output("out", "ref", "sweep"),
     rows=rows("out/runs.parquet"))
"""


OTHER_FILE = """
from probe_driver import run, same_output, rows, finished
first = finished("a.toml", "out")
again = run("-m", "wmrjax", "sweep", "b.toml", "--out", "out")
finished("b.toml", "ref")
emit(first=first, again=again, same=same_output("out", "ref", "sweep"), rows=rows("out/runs.parquet"))
"""


def _killed_oracle(run):
    """After kill -9, the rerun's table equals an uninterrupted run's (GOOD) or the rerun is
    refused by name (GOOD, for an edited file); another table with exit 0 is BAD."""
    if run.timed_out:
        return hang(run)
    r = run.results
    again = r["again"]
    where = f"killed with {r['blocks_at_kill']} blocks written" if "blocks_at_kill" in r else "run after the first"
    if again["rc"] == 0:
        if r["same"]:
            return GOOD, f"{where}; the rerun's table equals an uninterrupted run's"
        return BAD, f"{where}; exit 0 with a table ({r['rows']} rows) that is not the uninterrupted run's"
    if again["traceback"]:
        return POOR, f"{where}; rerun failed with a traceback: {short(again['last'])}"
    if re.search(r"another sweep|fingerprint|--fresh|--out", again["last"], re.I):
        return GOOD, f"{where}; refused: {short(again['last'])}"
    return POOR, f"{where}; rerun exit {again['rc']}: {short(again['last'])}"


def _killed() -> list[Case]:
    slow = specs.sweep(
        1.0,
        [
            ("t_final = 2.0", "t_final = 20.0"),
            ("block = 4", "block = 1"),
            ("x = [-0.5, 0.0, 0.7]", "x = { min = -0.5, max = 0.7, num = 6 }"),
            ("num = 3", "num = 6"),
        ],
    )
    edited = slow.replace("poles = 1.0", "poles = 2.0")
    return [
        Case(
            "sweep-killed-and-resumed",
            CAT,
            "a sweep killed with kill -9 between blocks, then the same command again (control)",
            _killed_oracle,
            code=KILLED.replace("RESUME", "slow.toml"),
            files={"slow.toml": slow},
            prelude="none",
            timeout=240,
        ),
        Case(
            "sweep-killed-resumed-with-edited-file",
            CAT,
            "a sweep killed with kill -9, its file edited (poles 2), then run again into the same --out",
            _killed_oracle,
            code=KILLED.replace("RESUME", "edited.toml"),
            files={"slow.toml": slow, "edited.toml": edited},
            prelude="none",
            timeout=240,
        ),
        Case(
            "sweep-other-file-same-out",
            CAT,
            "a finished sweep's --out reused by another sweep file (poles 2) without --fresh",
            _killed_oracle,
            code=OTHER_FILE,
            files=SWEEP_FILES,
            prelude="none",
            timeout=180,
        ),
    ]


# --- hand-edited tuning checkpoints (the library's tuner: wmrjax.tune.tune) -------------------------

CHECKPOINT = """
import json, os, shutil
import numpy as np
from wmrjax.problem import Problem
from wmrjax.tune import config, tune
P = Problem.from_dict(DATA)
TS = config.read(P.section("tune"))
setting = P.setting("tuning")
fam = TS.gain_family(setting)
def go(out, steps=None, **kw):
    steps = steps or TS.steps
    return tune(setting, fam, TS.optimizer.build(steps), steps=steps, scenarios=TS.scenarios, loss=TS.loss,
                stopping=TS.stopping, seed=TS.seed, out_dir=out, log=lambda *_: None, **kw)
go("ck", stop_after=2)
shutil.copytree("ck", "ck_orig")
path = "ck/checkpoint.json"
d = json.load(open(path))
def save(d):
    with open(path, "w") as f:
        json.dump(d, f)
EDIT
arm()
res = go("ck", **RESUME)
ref = go("ck_orig")
emit(same=bool(np.array_equal(np.asarray(res.raw), np.asarray(ref.raw))), raw=np.asarray(res.raw),
     ref=np.asarray(ref.raw), steps=len(res.history), ref_steps=len(ref.history))
"""


def _accepted_checkpoint(run):
    r = run.results
    if r.get("steps") != r.get("ref_steps"):
        return (
            BAD,
            f"accepted; the resumed run's history has {r.get('steps')} steps, the uninterrupted one's {r.get('ref_steps')}",
        )
    if r.get("same"):
        return POOR, f"accepted; resumed to the gains of the unedited checkpoint ({r.get('raw')})"
    return BAD, f"accepted; resumed to other gains: {r.get('raw')} instead of {r.get('ref')}"


def _control_checkpoint(run):
    r = run.results
    if r.get("same"):
        return GOOD, f"resumed to the uninterrupted run's gains {r.get('raw')}"
    return BAD, f"resumed to other gains: {r.get('raw')} instead of {r.get('ref')}"


def _checkpoint(cid: str, desc: str, edit: str, pattern: str, issue=False, resume="{}", control=False) -> Case:
    code = f"DATA = {specs.TUNE_DICT!r}\n" + CHECKPOINT.replace("EDIT", edit).replace("**RESUME", f"**{resume}")
    return Case(
        f"checkpoint-{cid}",
        CAT,
        f"a tuning checkpoint (after 2 of 4 steps) {desc}, then resumed",
        refuses(pattern, early=False, accepted=_control_checkpoint if control else _accepted_checkpoint),
        code=code,
        timeout=180,
        issue=issue,
    )


def _checkpoints() -> list[Case]:
    s = 'd["state"]'
    return [
        _checkpoint("step-true", 'with "step": true', 'd["step"] = True; save(d)', r"'?step'?", True),
        _checkpoint(
            "short-history",
            "with a history shorter than its step",
            f'{s}["history"] = {s}["history"][:1]; save(d)',
            "history",
            True,
        ),
        _checkpoint(
            "stopped-early-no",
            'with "stopped_early": "no"',
            f'{s}["stopped_early"] = "no"; save(d)',
            "stopped_early",
            True,
        ),
        _checkpoint(
            "rollouts-string", 'with "rollouts": "6" (a string)', f'{s}["rollouts"] = "6"; save(d)', "rollouts"
        ),
        _checkpoint(
            "best-raw-long",
            "with a best_raw of the wrong length",
            f'{s}["best_raw"] = [1.0, 2.0, 3.0]; save(d)',
            "best_raw",
        ),
        _checkpoint("step-negative", 'with "step": -1', 'd["step"] = -1; save(d)', r"'?step'?"),
        _checkpoint("step-beyond", 'with "step": 99 (the run has 4)', 'd["step"] = 99; save(d)', r"'?step'?"),
        _checkpoint("step-float", 'with "step": 1.5', 'd["step"] = 1.5; save(d)', r"'?step'?"),
        _checkpoint("history-not-list", 'with "history": "none"', f'{s}["history"] = "none"; save(d)', "history"),
        _checkpoint(
            "is-directory",
            "that is a directory",
            "os.remove(path); os.mkdir(path)",
            r"checkpoint\.json.*(directory|regular file)|(directory|regular file).*checkpoint",
            True,
        ),
        _checkpoint(
            "truncated",
            "truncated to half its length",
            "t = open(path).read(); open(path, 'w').write(t[: len(t) // 2])",
            r"checkpoint\.json",
        ),
        _checkpoint(
            "other-configuration",
            "of 4 steps, resumed as a run of 5",
            "pass",
            r"another configuration|fingerprint",
            resume="{'steps': 5}",
        ),
        _checkpoint(
            "unedited", "left as it is (control: resumes to the uninterrupted gains)", "pass", "^$", control=True
        ),
    ]


CLI_CHECKPOINT = """
from probe_driver import run, read_json
first = run("-m", "wmrjax", "tune", "tune.toml", "--out", "out")
gains = read_json("out/gains.json")
d = read_json("out/checkpoint.json")
d["step"] = True
import json
json.dump(d, open("out/checkpoint.json", "w"))
again = run("-m", "wmrjax", "tune", "tune.toml", "--out", "out")
emit(first=first, again=again, same=read_json("out/gains.json") == gains)
"""


def _cli_checkpoint_oracle(run):
    if run.timed_out:
        return hang(run)
    r = run.results
    again = r["again"]
    if again["rc"] == 0:
        if r["same"]:
            return POOR, "accepted; the gains are unchanged"
        return BAD, "exit 0; the gains changed: the edited step was taken as step 1 and the run continued"
    if again["traceback"]:
        return POOR, f"exit {again['rc']} with a traceback: {short(again['last'])}"
    if re.search(r"step", again["last"]) and "checkpoint" in again["last"]:
        return GOOD, f"refused (exit {again['rc']}): {short(again['last'])}"
    return POOR, f"exit {again['rc']}: {short(again['last'])}"


def cases() -> list[Case]:
    """Every data-loss case."""
    cli = Case(
        "tuning-cli-checkpoint-step-true",
        CAT,
        'a finished tuning\'s checkpoint.json edited to "step": true, then the same command again',
        _cli_checkpoint_oracle,
        code=CLI_CHECKPOINT,
        files={"tune.toml": specs.TUNE},
        prelude="none",
        timeout=180,
        issue=True,
    )
    return _concurrency() + _blocks() + _killed() + _checkpoints() + [cli]
