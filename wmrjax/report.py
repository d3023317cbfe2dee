"""What a job returns: every job's library function (:func:`wmrjax.certify.job.run`,
:func:`wmrjax.tune.job.run`, :func:`wmrjax.export.job.run`, :func:`wmrjax.identify.job.run`,
:func:`wmrjax.sweep.sweep`) returns a typed report, a frozen dataclass of that job's results,
and its plain-JSON summary (the job's ``summary.json``) through one method, :meth:`JobReport.summary`.

The command lines call the job's function, print from its report's fields and exit on its
alarms; a library user gets the same fields without reading a file back."""

from __future__ import annotations

import abc
from pathlib import Path

from wmrjax import _files as files


class JobReport(abc.ABC):
    """A job's result. Subclasses are frozen dataclasses whose fields are the job's results
    (typed records where the library has one: :class:`wmrjax.certify.CertificationReport`,
    :class:`wmrjax.identify.Identification`, ...) and implement :meth:`summary`."""

    @abc.abstractmethod
    def summary(self) -> dict:
        """The report as plain JSON (str, float, int, bool, None, lists and dicts): what the
        job writes as ``summary.json``; a fresh dict at every call."""

    def write_summary(self, out) -> Path:
        """Write :meth:`summary` atomically as ``out/summary.json``; returns that path.

        Args:
            out: the job's output directory (``str`` or ``Path``; it exists).
        """
        return files.write_json(Path(out) / "summary.json", self.summary())
