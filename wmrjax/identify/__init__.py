"""Identify the robot from its logs: the plant's geometry and input scales, the measurement noise
and an input delay, by maximum likelihood through the simulator, with 95 % intervals and the
parameters the logs cannot determine named (:func:`identify`); the log format and its checks
(:mod:`wmrjax.identify.logs`)."""

from wmrjax.identify import sections  # noqa: F401
from wmrjax.identify.fit import Estimate, FitOptions, Identification, PlantModel, identify, prediction_error  # noqa: F401
from wmrjax.identify.logs import Log, LogCheck, check_log, columns, log_from_columns, read_log  # noqa: F401
from wmrjax.identify.model import InputParams, LoggedInputs, LoggedState, predict  # noqa: F401

__all__ = [
    "Estimate",
    "FitOptions",
    "Identification",
    "InputParams",
    "Log",
    "LogCheck",
    "LoggedInputs",
    "LoggedState",
    "PlantModel",
    "check_log",
    "columns",
    "identify",
    "log_from_columns",
    "predict",
    "prediction_error",
    "read_log",
    "sections",
]
