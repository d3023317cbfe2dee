r"""A robot's logs: the format, reading it, and the checks that run before anything compiles.

A log is one recorded run of the robot, one row per controller sample (a CSV file with a header
line, :func:`read_log`; or any table's columns, :func:`log_from_columns`), with the columns

=================  ==========================================================================
``t``              time of the sample [s], strictly increasing, one controller period apart
``x``, ``y``       measured position of the body's reference point P [m]
``theta``          measured heading [rad]
``beta1``, ...     measured steering angles [rad], as many as the robot type has (delta_s)
``u1``, ...        the command sent at that sample, in the order of the type's input vector:
                   at velocity level :math:`(\eta, \zeta)` [m/s or rad/s] (eq 5), at torque
                   level the applied inputs :math:`v = \dot u` (eq 8); held until the next row
=================  ==========================================================================

Other columns are ignored, except ``beta<k>`` or ``u<k>`` beyond the type's count, which say the
log is of another robot type. The command of the last row is not used (nothing follows it).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from wmrjax import io
from wmrjax.robots import RobotType

# a sample period may differ from the stated one by this fraction (clock jitter)
PERIOD_RTOL = 1e-2


class Log(NamedTuple):
    """One recorded run (host arrays, float64).

    Attributes:
      name: what messages and reports call it (the file's name).
      t: (N,) sample times [s].
      posture: (N, 3 + delta_s) measured ``(x, y, theta, beta...)`` [m, m, rad, rad...].
      command: (N, delta_m + delta_s) the command held from each sample to the next.
    """

    name: str
    t: np.ndarray
    posture: np.ndarray
    command: np.ndarray


class LogCheck(NamedTuple):
    """What :func:`check_log` found in a log that is accepted.

    Attributes:
      n_samples: rows of the log.
      period: its mean sample period [s].
      saturated: per input, the rows whose command is beyond the plant's limit (the model clips
        them as the plant does; reported, not refused).
    """

    n_samples: int
    period: float
    saturated: tuple


def columns(robot: RobotType) -> tuple:
    """The columns a log of ``robot`` needs: ``t, x, y, theta, beta1.., u1..``."""
    betas = tuple(f"beta{i + 1}" for i in range(robot.delta_s))
    return ("t", "x", "y", "theta", *betas, *(f"u{i + 1}" for i in range(robot.n_input)))


def _foreign(header, robot: RobotType) -> list:
    """Columns of the header that a log of another robot type would have."""
    out = []
    for h in header:
        m = re.fullmatch(r"(beta|u)(\d+)", h)
        if m and int(m.group(2)) > (robot.delta_s if m.group(1) == "beta" else robot.n_input):
            out.append(h)
    return out


def read_log(path, robot: RobotType) -> Log:
    """Read one CSV log of ``robot`` (a Parquet log: :func:`log_from_columns` of its columns).

    Args:
      path: the file.
      robot: the robot type whose columns the log must have (:func:`columns`).

    Raises:
      ValueError: what :func:`wmrjax.io.read_csv_columns` refuses (a missing column, a value that
        is not a number, naming row and column), or columns of another robot type.
    """
    path = Path(path)
    what = f"log of a {robot.name} robot"
    try:
        data = io.read_csv_columns(path, columns(robot), what)
    except ValueError as err:
        raise ValueError(f"{err} (the log format: docs/experiments/identify)") from None
    return log_from_columns(path.name, data, io.csv_header(path, what), robot)


def log_from_columns(name: str, data: dict, header, robot: RobotType) -> Log:
    """A :class:`Log` of ``robot`` from a table's columns.

    Args:
      name: what messages call it.
      data: column name -> (N,) values, with every column of :func:`columns`.
      header: every column name of the table (to recognise another robot type's log).
      robot: the robot type.

    Raises:
      ValueError: a missing column, or columns of another robot type.
    """
    cols = columns(robot)
    what = f"log {io.excerpt(name, 200)} of a {robot.name} robot"
    missing = [c for c in cols if c not in data]
    if missing:
        raise ValueError(f"{what}: missing column(s) {missing}; a log needs {', '.join(cols)}")
    foreign = _foreign(header, robot)
    if foreign:
        raise ValueError(
            f"{what}: column(s) {foreign} belong to another robot type (a {robot.name} robot has "
            f"{robot.delta_s} steering angle(s) and {robot.n_input} input(s)): is this the log of another robot? "
            "Give the problem of that robot, or drop the columns"
        )
    values = {c: np.asarray(data[c], float).reshape(-1) for c in cols}
    posture = np.stack([values[c] for c in cols[1 : 4 + robot.delta_s]], axis=1)
    command = np.stack([values[c] for c in cols[4 + robot.delta_s :]], axis=1)
    return Log(name, values["t"], posture, command)


def check_log(log: Log, period: float | None, input_limit) -> LogCheck:
    """Refuse a log the fit cannot use, naming the row or column and the fix.

    Args:
      log: the log.
      period: the controller period it must be sampled at [s] (None: its own mean period, which
        must then be uniform).
      input_limit: (n_input,) the plant's limits (inf: none), for the saturation report.

    Raises:
      ValueError: fewer than two rows, a value that is not finite, time that does not increase, or
        a sample period other than ``period`` (within :data:`PERIOD_RTOL`).
    """
    name = io.excerpt(log.name, 80)
    n = len(log.t)
    if n < 2:
        raise ValueError(f"log {name}: {n} sample(s); a fit needs at least two (one controller period)")
    names = ("x", "y", "theta") + tuple(f"beta{i + 1}" for i in range(log.posture.shape[1] - 3))
    named = (("t",), names, tuple(f"u{i + 1}" for i in range(log.command.shape[1])))
    for cols, arr in zip(named, (log.t[:, None], log.posture, log.command)):
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            r, c = bad[0]
            raise ValueError(
                f"log {name}: data row {r + 1}, column {cols[c]!r} is {arr[r, c]} (every value must be finite): "
                "remove the row or fill it"
            )
    dt = np.diff(log.t)
    back = np.flatnonzero(dt <= 0)
    if back.size:
        r = int(back[0]) + 2
        raise ValueError(
            f"log {name}: data row {r} has t = {float(log.t[r - 1])!r} s, not after row {r - 1}'s {float(log.t[r - 2])!r} s; "
            "time must "
            "increase strictly (sort the rows, or split the log where it restarts)"
        )
    mean = float((log.t[-1] - log.t[0]) / (n - 1))
    target = mean if period is None else float(period)
    off = np.flatnonzero(np.abs(dt - target) > PERIOD_RTOL * target)
    if off.size:
        r = int(off[0]) + 2
        source = "its mean period" if period is None else "the controller period"
        raise ValueError(
            f"log {name}: data row {r} comes {dt[off[0]]:.6g} s after the previous one, not {source} {target:.6g} s "
            f"(within {PERIOD_RTOL:.0%}); a log has one row per controller sample"
            + ("" if period is None else " (state the log's period if it differs from the problem's control_period)")
        )
    limit = np.broadcast_to(np.asarray(input_limit, float), (log.command.shape[1],))
    saturated = tuple(int(np.sum(np.abs(log.command[:-1, i]) > limit[i])) for i in range(log.command.shape[1]))
    return LogCheck(n, mean, saturated)
