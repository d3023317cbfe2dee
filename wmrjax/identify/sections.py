"""From a problem to the model a fit needs, and from a fit back to the problem's ``[plant]``.

:func:`plant_model` reads what the problem knows (robot type, level, the law's geometry, the
plant's limits and controller period); :func:`plant_section` writes the identified ``[plant]``
section, each identified parameter's 95 % interval as a listed range (every job runs each
listed value: a sweep sweeps them, the tuner draws them, the real loop's falsifier searches
each), and :func:`with_plant_section` puts it into the problem file's text.
"""

from __future__ import annotations

import itertools
import math
import re

import numpy as np

from wmrjax.identify.fit import Identification, PlantModel
from wmrjax.problem import Setting


def plant_model(setting: Setting, period: float | None = None, substeps: int = 4) -> PlantModel:
    """The :class:`PlantModel` of a problem's setting.

    Args:
      setting: the problem's setting (one geometry, one set of limits).
      period: the logs' sample period [s] (default: the problem's ``[plant] control_period``).
      substeps: RK4 steps per period.

    Raises:
      ValueError: a problem with several geometries or limits, or no period from either source.
    """
    setting.check_single("identify", keep=("initial", "plant", "reference", "gains"))
    limits = np.unique(np.asarray(setting.axis("plant").payload["limit"]), axis=0)
    if len(limits) != 1:
        raise ValueError(f"identify takes one [plant] input_limit, got {len(limits)}: list one")
    period = setting.control_period if period is None else period
    if period is None:
        raise ValueError(
            "the logs' sample period is not known: give it (--period) or set the problem's [plant] control_period"
        )
    g = setting.geometry(0)
    geometry = type(g)(*(float(v) for v in g))
    return PlantModel(
        setting.ctrl.robot, setting.ctrl.level, geometry, tuple(float(v) for v in limits[0]), float(period), substeps
    )


def _number(v: float) -> str:
    return repr(float(v)) if math.isfinite(v) else "inf"


def _toml(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return _number(float(v))
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'


def plant_section(ident: Identification, plant: dict, source: str = "") -> str:
    """The ``[plant]`` section of the identified plant, as TOML text.

    Identified scales become listed ranges: ``geometry_scale`` its 95 % interval's two ends,
    ``input_scale`` the corners of the identified inputs' 95 % box (one factor per input; an input
    not identified keeps 1). ``noise_std`` is each channel's upper 95 % end (only with a
    ``control_period``: measurement noise needs a digital controller). The problem's other keys
    (limits, period, noise seed) are kept; a non-identifiable parameter keeps the problem's value,
    with the reason as a comment.

    Args:
      ident: the :class:`Identification`.
      plant: the problem's own ``[plant]`` table (``{}`` if none).
      source: what the comment at the top names as the logs.
    """
    lines = [
        f"# identified from {source}: 95 % intervals as listed ranges"
        if source
        else "# identified: 95 % intervals as listed ranges"
    ]
    lines.append("[plant]")
    for key in ("input_limit", "control_period"):
        if key in plant:
            lines.append(f"{key} = {_toml(plant[key])}")
    g = ident.parameters[0]
    if g.identifiable:
        lines.append(
            f"geometry_scale = {_toml(list(g.interval_95))}   # estimate {g.estimate:.6g} +- {g.std_error:.2g}"
        )
    else:
        if "geometry_scale" in plant:
            lines.append(f"geometry_scale = {_toml(plant['geometry_scale'])}")
        lines.append(f"# geometry_scale not identified: {g.note}")
    lines += _input_scale_lines(ident, plant)
    if "control_period" in plant:
        hi = [e.interval_95[1] for e in ident.noise_std]
        lines.append(f"noise_std = {_toml(hi)}   # upper 95 % ends [m, m, rad, rad...]")
        if "noise_seed" in plant:
            lines.append(f"noise_seed = {_toml(plant['noise_seed'])}")
    if ident.delay:
        lines.append(f"# an input delay of {ident.delay} sample(s) was identified; [plant] does not model it")
    return "\n".join(lines) + "\n"


def _input_scale_lines(ident: Identification, plant: dict) -> list:
    scales = ident.parameters[1:]
    ends = [list(e.interval_95) if e.identifiable else [1.0] for e in scales]
    if not any(e.identifiable for e in scales):
        out = [f"input_scale = {_toml(plant['input_scale'])}"] if "input_scale" in plant else []
        return out + ["# input_scale not identified"]
    corners = [list(c) for c in itertools.product(*ends)]
    est = ", ".join(f"{e.name} {e.estimate:.6g} +- {e.std_error:.2g}" for e in scales if e.identifiable)
    out = [f"input_scale = {_toml(corners)}   # the 95 % box's corners, one factor per input ({est})"]
    out += [f"# {e.name} not identified: {e.note}" for e in scales if not e.identifiable]
    return out


_HEADER = re.compile(r"^\s*\[\s*plant\s*\]\s*(#.*)?$")
_ANY_HEADER = re.compile(r"^\s*\[")


def with_plant_section(text: str, section: str) -> str:
    """A problem file's ``text`` with its ``[plant]`` section replaced by ``section`` (appended when
    it has none).

    Raises:
      ValueError: the text sets plant keys outside a ``[plant]`` header (dotted keys, an inline
        table), which a text edit cannot replace safely.
    """
    lines = text.splitlines()
    starts = [i for i, ln in enumerate(lines) if _HEADER.match(ln)]
    if not starts:
        if re.search(r"^\s*plant\s*[.=]", text, re.M):
            raise ValueError("the problem sets [plant] keys without a [plant] header; put them under one")
        return text.rstrip("\n") + "\n\n" + section
    i = starts[0]
    j = next((k for k in range(i + 1, len(lines)) if _ANY_HEADER.match(lines[k])), len(lines))
    return "\n".join(lines[:i] + section.rstrip("\n").splitlines() + [""] + lines[j:]) + "\n"
