"""Results on disk: atomic JSON/NPZ/bytes/PNG/Parquet writing, JSON checkpoints of pytrees, and
one writer per output directory.

The command lines' layer (installed with the ``cli`` extra): the library itself writes no
files, and reads a user's files with :mod:`wmrjax.io`. Matplotlib and pyarrow are imported
only by the functions that need them (:func:`headless_pyplot`, :func:`write_png`,
:func:`write_parquet`).

Every writer goes through :func:`atomic_write` (write a temporary file in the target
directory, then ``os.replace``), so a killed run leaves either the previous file or the
new one, never half of one. Nothing here loads a pickle: ``.npz`` files are written with
plain numeric arrays only, and checkpoints are JSON.
"""

from __future__ import annotations

import io as _io
import json
import os
import socket
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import io

# the temporary files of atomic_write end so (``.NAME.RANDOM.wmrjax-tmp``): a torn write's cleanup
# removes these and nothing else of a user's (a plain ``.tmp`` may be anybody's)
TMP_SUFFIX = ".wmrjax-tmp"


def atomic_write(path, write: Callable) -> Path:
    """Call ``write(fh)`` on a temporary binary file next to ``path``, then rename it to ``path``.

    The rename replaces a symbolic link at ``path`` (it is never written through), and a
    killed write leaves only a ``.NAME.*`` :data:`TMP_SUFFIX` file, which the next holder of
    the directory's lock removes."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TMP_SUFFIX)
    try:
        try:  # mkstemp makes 0600; results are as readable as the umask allows
            os.fchmod(fd, 0o666 & ~_umask())
        except OSError:  # file systems without modes: keep what they give
            pass
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _record(path)
    return path


def _umask() -> int:
    """The process umask (reading it means setting it for an instant: to the strictest one)."""
    mask = os.umask(0o077)
    os.umask(mask)
    return mask


def jsonable(x):
    """``x`` with arrays as lists, NamedTuples as dicts, and non-finite floats as None/"inf"/"-inf"."""
    if hasattr(x, "_asdict"):
        return jsonable(x._asdict())
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return jsonable(np.asarray(x).tolist())
    if isinstance(x, float) and not np.isfinite(x):
        return None if np.isnan(x) else ("inf" if x > 0 else "-inf")
    return x


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON atomically (see :func:`jsonable` for the conversions)."""
    data = json.dumps(jsonable(obj), indent=2, sort_keys=False).encode()
    return atomic_write(path, lambda fh: fh.write(data + b"\n"))


def write_npz(path, **arrays) -> Path:
    """Write an ``.npz`` of plain numeric/string arrays atomically.

    Raises:
      ValueError: for an object array (it would need a pickle to load).
    """
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    for k, v in arrays.items():
        if v.dtype == object:
            raise ValueError(f"refusing to save object array {k!r}: npz files here never hold pickles")
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


def write_bytes(path, data: bytes) -> Path:
    """Write raw bytes (e.g. a rendered PNG) atomically."""
    return atomic_write(path, lambda fh: fh.write(data))


# --- checkpoints -----------------------------------------------------------------------------


class Checkpoint(NamedTuple):
    """A resumable state: ``step`` done, the array pytrees, and a JSON-able ``state`` dict."""

    step: int
    trees: dict
    state: dict


def write_checkpoint(path, *, fingerprint: str, config: dict, step: int, trees: dict, state: dict) -> Path:
    """Write a JSON checkpoint atomically.

    Args:
      path: the checkpoint file (JSON).
      fingerprint: identifies the configuration; :func:`read_checkpoint` refuses another.
      config: the configuration itself (for the refusal message).
      step: steps completed.
      trees: name -> pytree of arrays (e.g. parameters, optimizer state), stored as leaf lists.
      state: any JSON-able dict (histories, counters).
    """
    leaves = {k: [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves(t)] for k, t in trees.items()}
    return write_json(
        path, {"fingerprint": fingerprint, "config": config, "step": step, "trees": leaves, "state": state}
    )


def read_checkpoint(path, *, fingerprint: str, config: dict, templates: dict) -> Checkpoint:
    """Read a checkpoint written by :func:`write_checkpoint`, restoring each tree's structure.

    Args:
      path: the checkpoint file (JSON).
      fingerprint: the configuration's; a checkpoint with another is refused.
      config: the configuration itself (the refusal names the keys that differ).
      templates: name -> a pytree with the expected structure, shapes and dtypes.

    Raises:
      ValueError: a checkpoint of another configuration (naming the keys that differ), or one
        whose trees do not match the templates (missing, truncated or reshaped leaves).
    """
    path = Path(path)
    if path.exists() and not path.is_file():
        raise ValueError(f"checkpoint {path} is not a regular file; remove it (or start fresh)")
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"checkpoint {path} is corrupt or truncated (not readable JSON: {exc}); "
            "delete it (or start fresh) to run from the beginning"
        ) from None
    if not isinstance(d, dict):
        raise ValueError(
            f"checkpoint {path} is not a checkpoint (a JSON {type(d).__name__}, expected an object); "
            "delete it (or start fresh) to run from the beginning"
        )
    for key in ("config", "trees", "state"):
        if key in d and not isinstance(d[key], dict):
            raise ValueError(
                f"checkpoint {path}: '{key}' is a JSON {type(d[key]).__name__}, expected an object "
                "(an edited or corrupt checkpoint)"
            )
    if d.get("fingerprint") != fingerprint:
        old = d.get("config", {}) or {}
        diff = sorted(
            k
            for k, v in config.items()
            if json.loads(json.dumps(jsonable(old.get(k)))) != json.loads(json.dumps(jsonable(v)))
        )
        raise ValueError(
            f"checkpoint {path} belongs to another configuration (differs in {diff}); "
            "use another --out directory or delete the checkpoint"
        )
    trees = {}
    for name, template in templates.items():
        got = (d.get("trees") or {}).get(name)
        tmpl, treedef = jax.tree_util.tree_flatten(template)
        if got is not None and not isinstance(got, list):
            raise ValueError(
                f"checkpoint {path}: tree {name!r} is a JSON {type(got).__name__}, expected a list of leaves"
            )
        if got is None or len(got) != len(tmpl):
            raise ValueError(
                f"checkpoint {path}: tree {name!r} has {None if got is None else len(got)} leaves, expected {len(tmpl)}"
            )
        leaves = []
        for i, (v, t) in enumerate(zip(got, tmpl)):
            try:
                a = np.asarray(v, dtype=np.asarray(t).dtype)
            except (TypeError, ValueError) as exc:
                raise ValueError(
                    f"checkpoint {path}: leaf {i} of {name!r} is not a numeric array ({exc}); "
                    "an edited or corrupt checkpoint"
                ) from None
            if a.shape != np.shape(t):
                raise ValueError(
                    f"checkpoint {path}: leaf {i} of {name!r} has shape {a.shape}, expected "
                    f"{np.shape(t)} (a truncated or edited checkpoint)"
                )
            leaves.append(jnp.asarray(a))
        trees[name] = jax.tree_util.tree_unflatten(treedef, leaves)
    # bool is an int in Python: "step": true would be taken as step 1
    if type(d.get("step")) is not int or d["step"] < 0 or not isinstance(d.get("state"), dict):
        raise ValueError(
            f"checkpoint {path} lacks an integer 'step' >= 0 or a 'state' object (got step "
            f"{d.get('step')!r}); an edited or corrupt checkpoint: delete it (or start fresh)"
        )
    return Checkpoint(d["step"], trees, d["state"])


# --- figures -----------------------------------------------------------------------------------


def headless_pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (for writing PNG files)."""
    import matplotlib  # optional dependency (the cli extra): only a figure needs it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional dependency (the cli extra): only a figure needs it

    return plt


def write_png(fig, path, dpi: int = 120) -> Path:
    """Render a matplotlib figure to PNG and write it atomically."""
    buf = _io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return write_bytes(path, buf.getvalue())


def write_parquet(path, batches) -> Path:
    """Stream ``pyarrow.RecordBatch`` es into a Parquet file, one row group each, atomically.

    Memory stays at one batch whatever the number of rows; the file appears (by rename) only
    when complete. Needs ``pyarrow``.

    Args:
      path: target ``.parquet`` path.
      batches: an iterable of record batches sharing one schema (the first batch's).
    """
    import pyarrow.parquet as pq  # optional dependency (the cli extra): only the Parquet table needs it

    def write(fh):
        writer = None
        try:
            for batch in batches:
                if writer is None:
                    writer = pq.ParquetWriter(fh, batch.schema)
                writer.write_batch(batch)
        finally:
            if writer is not None:
                writer.close()

    return atomic_write(path, write)


def read_parquet_columns(path, cols: tuple, what: str) -> tuple:
    """``(columns, header)`` of a Parquet file: name -> float64 (n,) for each of ``cols``, and
    every column name. Needs ``pyarrow``.

    Raises:
      ValueError: not a regular file, larger than :data:`wmrjax.io.MAX_FILE_BYTES`, not Parquet, or
        a missing column; naming the file.
    """
    import pyarrow.parquet as pq  # optional dependency (the cli extra): only the Parquet table needs it

    path = Path(path)
    name = io.excerpt(str(path), 200)
    if not path.is_file():
        raise ValueError(f"{what} {name}: not a regular file (missing, or a directory or device)")
    if path.stat().st_size > io.MAX_FILE_BYTES:
        raise ValueError(f"{what} {name}: more than {io.MAX_FILE_BYTES} bytes")
    try:
        header = list(pq.read_schema(path).names)
    except Exception as err:  # pyarrow raises its own error types for a file that is not Parquet
        raise ValueError(f"{what} {name}: not a Parquet file ({io.excerpt(str(err))})") from None
    missing = [c for c in cols if c not in header]
    if missing:
        raise ValueError(f"{what} {name}: missing column(s) {missing}; it needs {', '.join(cols)}")
    table = pq.read_table(path, columns=list(cols))
    return {c: np.asarray(table.column(c).to_numpy(), float) for c in cols}, header


# --- one writer per output directory ---------------------------------------------------------

LOCK_NAME = ".wmrjax-writer.lock"
# a process given this variable (a sweep's --processes workers) writes under its parent's lock
LOCK_ENV = "WMRJAX_OUTPUT_LOCK"


class OutputLocked(ValueError):
    """Another live process is writing to the output directory."""


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux), None if unknown or dead.
    With the pid it identifies a process: a reused pid has another start time."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            stat = fh.read().decode(errors="replace")
        return stat[stat.rindex(")") + 2 :].split()[19]  # field 22, after the command name
    except (OSError, ValueError, IndexError):
        return None


def _alive(owner: dict) -> bool:
    """Whether the lock's owner is a live process on this host."""
    if owner.get("host") != socket.gethostname():
        return True  # another host's process: cannot tell, assume alive
    pid = owner.get("pid")
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return False
    start = _process_start(pid)
    if start is not None:
        return start == owner.get("start")
    try:  # no /proc: is the pid in use at all?
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _read_owner(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
        return d if isinstance(d, dict) else {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return {}


def acquire_output(out, command: str) -> str | None:
    """Make this process the one writer of directory ``out``; returns the lock's token (for
    :func:`release_output`, and :data:`LOCK_ENV` of workers), None for a worker of its owner.

    The lock is a file created exclusively (``O_EXCL``) in ``out`` holding the owner's host,
    process id, process start time and command. A lock whose owner is dead (on this host) is
    stale: it is named on stderr and taken over. A process whose environment carries
    :data:`LOCK_ENV` equal to the lock's token writes under it (a parent's workers), and so does
    the owner itself (a command run again in the same process). Once the
    lock is held, temporary files a killed atomic write left in ``out`` are removed.

    Raises:
      OutputLocked: a live process (named) holds the lock.
    """
    out = Path(out)
    path = out / LOCK_NAME
    token = uuid.uuid4().hex
    me = {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "start": _process_start(os.getpid()),
        "command": command,
        "since": time.strftime("%Y-%m-%d %H:%M:%S"),
        "token": token,
    }
    for _ in range(100):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _read_owner(path)
            if owner.get("token") and owner.get("token") == os.environ.get(LOCK_ENV):
                return None  # a worker of the lock's owner
            if owner.get("pid") == me["pid"] and owner.get("host") == me["host"] and owner.get("start") == me["start"]:
                return None  # this process holds it already (a command run again in-process)
            if not owner and time.time() - path.stat().st_mtime < 5.0:
                time.sleep(0.05)  # being written this instant
                continue
            if owner and _alive(owner):
                raise OutputLocked(
                    f"{out} is being written by another run: process {owner.get('pid')} on {owner.get('host')} "
                    f"({owner.get('command')!r}, since {owner.get('since')}); wait for it to finish, or choose "
                    f"another output directory (if that process is gone, delete {path})"
                ) from None
            stale = path.with_name(f"{LOCK_NAME}.stale-{token}")
            try:  # one taker renames it; the others retry
                os.rename(path, stale)
            except FileNotFoundError:
                continue
            os.unlink(stale)
            print(
                f"{out}: removed the stale lock of process {owner.get('pid')} ({owner.get('command')!r}, "
                f"since {owner.get('since')}), which is no longer running",
                file=sys.stderr,
            )
            continue
        with os.fdopen(fd, "w") as fh:
            json.dump(me, fh)
        _remove_torn_writes(out)
        return token
    raise OutputLocked(f"could not take the lock {path}: it changed hands 100 times")


# which job's results a directory holds (written by the first job that writes there)
JOB_NAME = ".wmrjax-job.json"


def claim_output(out, job: str, fresh: bool = False) -> list[str]:
    """Record that ``out`` holds ``job``'s results, or refuse a directory that holds another
    job's: a certification into a finished sweep's directory replaced its summary.json and left
    the sweep's table beside it. With ``fresh`` the other job's results are removed instead
    (:func:`discard_results`: only the files it recorded writing). Call while holding the lock
    (:func:`acquire_output`). Returns the relative paths removed.

    Raises:
      OutputLocked: ``out`` holds the results of another job (named), and not ``fresh``.
    """
    path = Path(out) / JOB_NAME
    owner = _read_owner(path) if path.is_file() and not path.is_symlink() else {}
    removed = []
    if owner.get("job") not in (None, job):
        if not fresh:
            raise OutputLocked(
                f"{out} holds the results of {owner['job']!r}, not of {job!r}: one directory holds one job's "
                f"results; rerun with --fresh to remove them (only the files {owner['job']!r} recorded "
                "writing), or choose another output directory"
            )
        removed = discard_results(out)
    if owner.get("job") != job:
        write_json(path, {"job": job})
    return removed


# a job's record of what it wrote in its output directory: one relative path per line, in a file
# per process (a sweep's workers append to their own, so lines never interleave)
MANIFEST_PREFIX = ".wmrjax-files."
_RECORDING: list[Path] = []  # the output directories this process writes under


def record_writes(out) -> None:
    """Record every later atomic write (:func:`atomic_write`) of this process under directory
    ``out`` in its manifest there, for :func:`discard_results`."""
    root = Path(out).resolve()
    if root not in _RECORDING:
        _RECORDING.append(root)


def _record(path: Path) -> None:
    """Append ``path`` to the manifest of each recorded output directory holding it."""
    if not _RECORDING:
        return
    real = Path(path).resolve()
    for root in _RECORDING:
        if real != root and real.is_relative_to(root) and real.name != JOB_NAME:
            with open(root / f"{MANIFEST_PREFIX}{os.getpid()}", "a", encoding="utf-8") as fh:
                fh.write(f"{real.relative_to(root)}\n")


def discard_results(out) -> list[str]:
    """Remove from ``out`` what the jobs that wrote there recorded writing (their manifests'
    files), the manifests and the job record; returns the relative paths removed.

    Only regular files inside ``out`` are removed, never through a link (a path whose real
    location is outside ``out``, or a link itself, stays); directories the removed files leave
    empty are removed. A user's own files were never recorded and stay, and so do files written
    before manifests were kept (2026-11-29)."""
    out = Path(out)
    root = out.resolve()
    removed, seen = [], set()  # a file written again is listed again (a sweep's state, a summary)
    for manifest in sorted(out.glob(MANIFEST_PREFIX + "*")):
        if manifest.is_symlink() or not manifest.is_file():
            continue
        for line in manifest.read_text(encoding="utf-8", errors="replace").splitlines():
            rel = Path(line)
            p = out / rel
            if not line or rel.is_absolute() or ".." in rel.parts or p.is_symlink() or not p.is_file():
                continue
            if p.resolve().is_relative_to(root) and line not in seen:
                p.unlink()
                removed.append(line)
                seen.add(line)
        manifest.unlink()
    (out / JOB_NAME).unlink(missing_ok=True)
    for d in sorted({(out / r).parent for r in removed}, key=lambda d: len(d.parts), reverse=True):
        while d != out and d.is_dir() and not d.is_symlink() and not any(d.iterdir()):
            d.rmdir()
            d = d.parent
    return removed


def release_output(out, token: str | None) -> None:
    """Remove the lock of ``out`` if ``token`` holds it (a no-op for None)."""
    path = Path(out) / LOCK_NAME
    if token is not None and _read_owner(path).get("token") == token:
        path.unlink(missing_ok=True)


def _remove_torn_writes(out: Path) -> None:
    """Delete the temporary files of killed atomic writes (``.NAME.*`` :data:`TMP_SUFFIX`, see
    :func:`atomic_write`) in ``out`` and its subdirectories, not following links: only those
    this package's writer names so, so a user's own ``.x.tmp`` stays."""
    for root, _, names in os.walk(out, followlinks=False):
        for name in names:
            p = Path(root) / name
            if name.startswith(".") and name.endswith(TMP_SUFFIX) and p.is_file() and not p.is_symlink():
                p.unlink(missing_ok=True)
