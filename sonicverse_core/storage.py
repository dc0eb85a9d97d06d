"""Files that survive a crash: atomic replacement and append-only record logs.

* :func:`atomic_write` writes to a temporary file in the target's folder, fsyncs it, renames it over the target and
  fsyncs the folder: a reader (or a kill at any moment) sees the old file or the new one, never a torn one.
* :class:`RecordLog` appends fixed-size binary records (a numpy structured dtype) behind a one-line JSON header and
  flushes them to the disk every ``sync_every`` records; :func:`read_records` reads every whole record back and
  ignores a torn last one, so a SIGKILL loses at most the records since the last sync.
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from sonicverse_core.errors import DataError

MAGIC = b"SVLOG1\n"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # a platform without directory handles: the rename is still atomic
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path, mode: str = "wb"):
    """``with atomic_write(p) as fh: fh.write(...)``: the file appears whole at ``p`` when the block ends without
    an exception, and not at all (the old one stays) otherwise."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # name the file asked for, not the temporary one beside it
        raise OSError(exc.errno, f"cannot write there ({exc.strerror})", str(path)) from exc
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would make results private
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text_atomic(path, text: str) -> Path:
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return Path(path)


def dtype_spec(dtype: np.dtype) -> list:
    """A JSON form of a structured dtype (``np.dtype(spec)`` rebuilds it)."""
    return [[name, dtype.fields[name][0].base.str, list(dtype.fields[name][0].shape)] for name in dtype.names]


class RecordLog:
    """Append-only file of fixed-size records: ``MAGIC``, one JSON header line (``meta`` + the dtype), then the
    records. ``append`` takes one record (a tuple or a 0-d structured array)."""

    def __init__(self, path, dtype: np.dtype, meta: dict, sync_every: int = 90):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.dtype = np.dtype(dtype)
        self.sync_every = max(1, int(sync_every))
        self.count = 0
        self._fh = open(self.path, "wb")
        self._fh.write(MAGIC + json.dumps({**meta, "dtype": dtype_spec(self.dtype)}).encode() + b"\n")
        self.sync()

    def append(self, record) -> None:
        self._fh.write(np.asarray(record, self.dtype).tobytes())
        self.count += 1
        if self.count % self.sync_every == 0:
            self.sync()

    def sync(self) -> None:
        if self._fh is not None:
            self._fh.flush()
            os.fsync(self._fh.fileno())

    def close(self) -> None:
        if self._fh is not None:
            self.sync()
            self._fh.close()
            self._fh = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_records(path) -> tuple[dict, np.ndarray]:
    """(meta, records) of a :class:`RecordLog` file; a torn last record (a kill mid-write) is left out."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read '{path}': {exc.strerror}") from None
    if not raw.startswith(MAGIC) or b"\n" not in raw[len(MAGIC):]:
        raise DataError(f"'{path}' is not a Sonicverse record log (no header: empty, truncated or another format)")
    end = raw.index(b"\n", len(MAGIC))
    try:
        meta = json.loads(raw[len(MAGIC):end])
        dtype = np.dtype([(n, t, tuple(s)) for n, t, s in meta.pop("dtype")])
    except (ValueError, TypeError, KeyError) as exc:
        raise DataError(f"'{path}': corrupt header ({exc})") from None
    body = raw[end + 1:]
    whole = len(body) // dtype.itemsize * dtype.itemsize
    return meta, np.frombuffer(body[:whole], dtype).copy()
