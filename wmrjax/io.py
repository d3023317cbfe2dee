"""Reading a user's small files: problem, gains and samples files (:func:`read_small_text`) and
the columns of a CSV file (:func:`read_csv_columns`), bounded in size and refused with a
message naming the file.

The library writes nothing: results on disk (atomic writers, checkpoints, output locks) are
the command lines' layer, :mod:`wmrjax._files`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# --- reading a user's small files -------------------------------------------------------------

# a problem, gains or samples file larger than this is not one (a device such as /dev/zero, or
# the wrong file): refused before reading, as reading it would not end or would fill memory
MAX_FILE_BYTES = 64 * 2**20


# a message quotes at most this many characters of anything read from a user's file (a header,
# a value) or of its path: never a file's content at length (a samples "file" that is
# /proc/self/environ would print the environment, secrets included)
EXCERPT_CHARS = 60
# a CSV header line longer than this is not one
MAX_HEADER_CHARS = 4096


def excerpt(text: str, limit: int = EXCERPT_CHARS) -> str:
    """``repr`` of at most ``limit`` characters of ``text``, with the length of what was left out."""
    text = str(text)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


def _name(path) -> str:
    """A path as messages quote it: in full unless it is very long."""
    return excerpt(str(path), 200)


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
            raise ValueError(f"{what} {_name(path)}: not a regular file (missing, or a directory or device)")
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ValueError(f"{what} {_name(path)}: {size} bytes, more than {MAX_FILE_BYTES}")
        with open(path, "rb") as fh:  # bounded even if the file grew since stat
            data = fh.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:
            raise ValueError(f"{what} {_name(path)}: more than {MAX_FILE_BYTES} bytes")
        if b"\x00" in data:
            raise ValueError(f"{what} {_name(path)}: contains NUL bytes, so it is not a text file")
        return data.decode("utf-8-sig")
    except OSError as err:
        raise ValueError(f"cannot read {what} {_name(path)}: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ValueError(f"{what} {_name(path)} is not UTF-8 text ({err.reason} at byte {err.start})") from None


def _lines(path, what: str) -> list:
    """The non-empty, non-comment lines of a small text file."""
    text = read_small_text(path, what)
    return [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def csv_header(path, what: str) -> list:
    """The column names of a small CSV file's header line (stripped; ``[]`` for an empty file).

    Raises:
      ValueError: what :func:`read_small_text` refuses, or a header line longer than
        :data:`MAX_HEADER_CHARS`.
    """
    lines = _lines(path, what)
    if lines and len(lines[0]) > MAX_HEADER_CHARS:
        raise ValueError(
            f"{what} {_name(path)}: its header line has {len(lines[0])} characters (at most {MAX_HEADER_CHARS})"
        )
    return [h.strip() for h in lines[0].split(",")] if lines else []


def read_csv_columns(path, cols: tuple, what: str) -> dict:
    """The named columns of a small CSV file with a header line (``#`` starts a comment; other
    columns are ignored, whatever they hold). Messages quote at most :data:`EXCERPT_CHARS`
    characters of the file.

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
    lines = _lines(path, what)
    if not lines:
        raise ValueError(f"{what} {_name(path)}: no header line; expected a CSV file with columns {', '.join(cols)}")
    if len(lines[0]) > MAX_HEADER_CHARS:
        raise ValueError(
            f"{what} {_name(path)}: its header line has {len(lines[0])} characters (at most {MAX_HEADER_CHARS}); "
            f"expected a line naming the columns, with {', '.join(cols)} among them"
        )
    header = [h.strip() for h in lines[0].split(",")]
    shown = ", ".join(excerpt(h, 20) for h in header[:8]) + (
        f", ... ({len(header)} columns)" if len(header) > 8 else ""
    )
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ValueError(
            f"{what} {_name(path)}: column(s) {[d if len(d) <= 20 else d[:20] + '...' for d in dup]} appear more than once in "
            f"the header [{shown}]"
        )
    missing = [c for c in cols if c not in header]
    if missing:
        raise ValueError(
            f"{what} {_name(path)}: missing column(s) {missing}; the header must name {', '.join(cols)} (got [{shown}])"
        )
    index = [header.index(c) for c in cols]
    rows = np.empty((len(lines) - 1, len(cols)))
    for r, ln in enumerate(lines[1:]):
        values = ln.split(",")
        if len(values) != len(header):
            raise ValueError(
                f"{what} {_name(path)}: data row {r + 1} has {len(values)} values; every row needs {len(header)} "
                "like the header"
            )
        for j, i in enumerate(index):
            try:
                rows[r, j] = float(values[i])
            except ValueError:
                raise ValueError(
                    f"{what} {_name(path)}: data row {r + 1}, column {cols[j]!r}: {excerpt(values[i].strip(), 30)} "
                    "is not a number"
                ) from None
    if rows.shape[0] == 0:
        raise ValueError(f"{what} {_name(path)}: a header and no data rows")
    return {c: rows[:, j] for j, c in enumerate(cols)}
