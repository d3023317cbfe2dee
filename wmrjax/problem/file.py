"""A user's problem: :class:`Problem`, the file (TOML) or dict every job reads, validated whole when
it is built; its cases; its settings; and its resolved form (every file it reads inlined).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import importlib
import json
import tomllib
from pathlib import Path

from wmrjax.problem.gains_file import read_gains_file
from wmrjax.problem.reference import family_of
from wmrjax.problem.schema import (
    CASE_NAME,
    CASE_NAME_MAX,
    CASE_SECTIONS,
    JOB_SECTIONS,
    SECTIONS,
    ProblemError,
    check_keys,
    read_csv,
    read_text,
)
from wmrjax.problem.sections import settings_of
from wmrjax.problem.setting import Setting


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A user's problem (see the module docstring for its file form).

    Attributes:
      data: the problem as parsed TOML (plain JSON types); checked when built.
      base: the directory relative file names resolve against (the file's own directory).
      source: the file it was read from (None if built in Python).
    """

    data: dict
    base: Path = dataclasses.field(default_factory=Path.cwd)
    source: Path | None = None

    def __post_init__(self):
        # every key validated now, before anything compiles; the settings are kept (immutable data)
        object.__setattr__(self, "_settings", self._validated())

    @classmethod
    def load(cls, path) -> "Problem":
        """Read and validate a problem file (TOML)."""
        path = Path(path)
        text = read_text(path, "problem file")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ProblemError(f"{path}: not valid TOML: {err}") from None
        return cls(data, path.resolve().parent, path)

    @classmethod
    def from_dict(cls, data: dict, base=None) -> "Problem":
        """A problem from its sections as a dict (the TOML tree; e.g. a summary's ``problem``)."""
        if not isinstance(data, dict):
            raise ProblemError(f"a problem is a table of sections, got {type(data).__name__}")
        return cls(copy.deepcopy(data), Path.cwd() if base is None else Path(base))

    def with_values(self, values: dict) -> "Problem":
        """A copy with values set by dotted keys, validated (e.g. ``{"plant.input_limit": [2.0, 1.5],
        "tune.optimizer.learning_rate": 0.1}``; ``None`` deletes a key). Command lines apply
        their options to a problem file this way."""
        data = copy.deepcopy(self.data)
        for key, v in values.items():
            *path, last = key.split(".")
            node = data
            for k in path:
                node = node.setdefault(k, {})
                if not isinstance(node, dict):
                    raise ProblemError(f"{key}: {k} is not a table in this problem")
            if v is None:
                node.pop(last, None)
            else:
                node[last] = v
        return Problem(data, self.base, self.source)

    @property
    def title(self) -> str:
        """The problem's title (its ``title``, else the file's stem)."""
        return str(self.data.get("title", self.source.stem if self.source else "problem"))

    def section(self, name: str) -> dict:
        """A job's own section (``tune``, ``certify``, ``classify``), {} if absent."""
        s = self.data.get(name, {})
        check_keys(name, s, s.keys() if isinstance(s, dict) else ())
        return s

    def cases(self) -> list:
        """``(name, data)`` for every case: the problem itself (name None) when it has no ``[[case]]``."""
        cases = self.data.get("case")
        if cases is None:
            return [(None, self.data)]
        if not isinstance(cases, list) or not cases or not all(isinstance(c, dict) for c in cases):
            raise ProblemError("[[case]]: expected an array of tables, each with a name and the sections it changes")
        out, names = [], set()
        for i, c in enumerate(cases):
            check_keys(f"case #{i + 1}", c, ("name",) + CASE_SECTIONS, ("name",))
            name = c["name"]
            if not isinstance(name, str) or not CASE_NAME.fullmatch(name) or name in names:
                shown = repr(name)
                raise ProblemError(
                    f"[[case]] #{i + 1} name: expected a label of 1 to {CASE_NAME_MAX} characters -- letters, "
                    "digits, space, '_', '.', '+', '-', starting with a letter or digit (it names the case's "
                    f"figures and rows) -- not used by another case, got "
                    f"{shown[:60] + '...' if len(shown) > 60 else shown}"
                )
            names.add(name)
            merged = {k: v for k, v in self.data.items() if k != "case"}
            merged.update({k: v for k, v in c.items() if k != "name"})
            out.append((name, merged))
        return out

    def settings(self) -> list:
        """One :class:`Setting` per case, robot type and level, every key validated."""
        return list(self._settings)

    def _validated(self) -> list:
        unknown = sorted(set(self.data) - set(SECTIONS))
        if unknown:
            raise ProblemError(f"unknown section(s) {unknown}; expected some of {list(SECTIONS)}")
        for name, module in JOB_SECTIONS.items():
            if name in self.data:  # the job's own schema, from the module that owns it
                importlib.import_module(module).read_section(self.data)
        out = []
        for name, data in self.cases():
            out += settings_of(data, self.base, name)
        return out

    def setting(self, job: str, case: str | None = None) -> "Setting":
        """The one setting a job runs (``job`` names it in messages): one robot, one level, and
        one case (or ``case``)."""
        settings = self.settings()
        if case is not None:
            settings = [s for s in settings if s.case == case]
            if not settings:
                raise ProblemError(f"no case named {case!r}; the problem has {[c for c, _ in self.cases()]}")
        if len(settings) != 1:
            which = sorted({(s.case, s.ctrl.robot.name, str(s.ctrl.level)) for s in settings}, key=str)
            raise ProblemError(
                f"{job} takes one controller: this problem has {len(settings)} settings {which} "
                "(a list of robots or levels, or several [[case]]s); keep one"
                + (" or choose a case" if len({s.case for s in settings}) > 1 else "")
            )
        return settings[0]

    def resolved(self) -> dict:
        """The problem as plain JSON with every file it reads inlined (reference samples, gains),
        so that it runs again from this dict alone (:meth:`from_dict`)."""
        data = copy.deepcopy(self.data)
        sections = [data] + list(data.get("case", []))
        for sec in sections:
            ref = sec.get("reference")
            family = family_of(ref)
            if family is not None and family.kind == "data" and "file" in ref:
                path = self.base / ref["file"]
                cols = read_csv(path, family.columns)
                ref.pop("file")
                ref.update({k: v.tolist() for k, v in cols.items()})
                ref["source_file"] = {"path": str(path), "sha256": _digest(path)}
            gains = sec.get("gains")
            if isinstance(gains, dict) and isinstance(gains.get("file"), str):
                path = self.base / gains["file"]
                sec["gains"] = {
                    **read_gains_file(path).to_problem(),
                    "source_file": {"path": str(path), "sha256": _digest(path)},
                }
        return data

    def fingerprint(self) -> str:
        """A digest of the resolved problem (files included): equal problems, equal fingerprints."""
        return hashlib.sha256(json.dumps(self.resolved(), sort_keys=True).encode()).hexdigest()[:16]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
