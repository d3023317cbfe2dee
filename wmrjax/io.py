"""Reading a user's small files: problem, gains and samples files (:func:`read_small_text`) and
the columns of a CSV file (:func:`read_csv_columns`), bounded in size and refused with a
message naming the file.

The library writes nothing: results on disk (atomic writers, checkpoints, output locks) are
the command lines' layer, :mod:`wmrjax_cli.files`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# --- reading a user's small files -------------------------------------------------------------

# a problem, gains or samples file larger than this is not one (a device such as /dev/zero, or
# the wrong file): refused before reading, as reading it would not end or would fill memory
MAX_FILE_BYTES = 64 * 2**20


def read_small_text(path, what: str) -> str:
    """The text of a small UTF-8 file (a spreadsheet's byte-order mark dropped).

    Args:
      path: the file.
      what: what it is, for the messages (e.g. ``"[gains] file"``).

    Raises:
      ValueError: not a regular file (missing, a directory, a device such as ``/dev/zero``),
        larger than :data:`MAX_FILE_BYTES`, unreadable, or not UTF-8; naming the file.
    """
    path = Path(path)
    try:
        if not path.is_file():
            raise ValueError(f"{what} {str(path)!r}: not a regular file (missing, or a directory or device)")
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{what} {str(path)!r}: {size} bytes, more than {MAX_FILE_BYTES}")
        with open(path, "rb") as fh:  # bounded even if the file grew since stat
            data = fh.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:
            raise ValueError(f"{what} {str(path)!r}: more than {MAX_FILE_BYTES} bytes")
        return data.decode("utf-8-sig")
    except OSError as err:
        raise ValueError(f"cannot read {what} {str(path)!r}: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{what} {str(path)!r} is not UTF-8 text ({err.reason} at byte {err.start})") from None


def read_csv_columns(path, cols: tuple, what: str) -> dict:
    """The named columns of a small CSV file with a header line (``#`` starts a comment; other
    columns are ignored).

    Args:
      path: the file (read by :func:`read_small_text`).
      cols: the column names needed, e.g. ``("t", "x", "y")``.
      what: what it is, for the messages.

    Returns:
      name -> float64 array (n,) for each of ``cols``.

    Raises:
      ValueError: what :func:`read_small_text` refuses, a header naming a column twice (which
        one would be meant?), a missing column, a value that is not a number, or a ragged row.
    """
    text = read_small_text(path, what)
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{what} {str(path)!r}: no header line; expected a CSV file with columns {', '.join(cols)}")
    header = [h.strip() for h in lines[0].split(",")]
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ValueError(f"{what} {str(path)!r}: column(s) {dup} appear more than once in the header {header}")
    missing = [c for c in cols if c not in header]
    if missing:
        raise ValueError(
            f"{what} {str(path)!r}: missing column(s) {missing}; the header must name {', '.join(cols)} (got {header})"
        )
    try:
        rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]], float)
    except ValueError as err:
        raise ValueError(f"{what} {str(path)!r}: a value is not a number ({err})") from None
    if rows.ndim != 2 or rows.shape[0] == 0 or rows.shape[1] != len(header):
        raise ValueError(f"{what} {str(path)!r}: every row needs {len(header)} values like the header")
    return {c: rows[:, header.index(c)] for c in cols}
