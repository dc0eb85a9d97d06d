"""Lock-free structures shared between the main loop and the audio callback, over one flat memory block.

The block is an ``mmap`` of an anonymous memory file (:class:`SharedBlock`: nothing named in /dev/shm) when the
audio runs in its own process, or a plain ``bytearray`` when it runs in a thread; both sides build the same numpy views over it with :class:`Layout`.

* :class:`Ring`: single-producer single-consumer ring of float32 frames. The producer writes the samples, then
  publishes a monotonically increasing frame counter (one aligned int64 store); it never waits. Each consumer keeps
  its own read counter; a consumer that falls more than the capacity behind skips ahead and counts the frames lost.
* :class:`SeqLock`: one writer publishes a float64 vector (the poses of one frame); the reader copies it and
  retries when the sequence number was odd or changed during the copy, so it never sees a torn frame and never
  blocks the writer.

Ordering relies on x86-64's total store order (stores become visible in program order; aligned 8-byte stores are
atomic), which is where this runs; numpy performs each store below as one plain machine store.
"""
from __future__ import annotations

import mmap
import os
import tempfile
from dataclasses import dataclass, field

import numpy as np

_ALIGN = 64  # a cache line: counters written by one side never share a line with the other side's data


@dataclass
class Layout:
    """Named numpy arrays at fixed offsets in one block. ``add`` reserves, ``views`` maps a buffer."""

    entries: list = field(default_factory=list)
    size: int = 0

    def add(self, name: str, shape, dtype) -> None:
        dtype = np.dtype(dtype)
        shape = tuple(int(s) for s in np.atleast_1d(shape))
        self.entries.append((name, shape, dtype.str, self.size))
        nbytes = int(np.prod(shape)) * dtype.itemsize
        self.size += (nbytes + _ALIGN - 1) // _ALIGN * _ALIGN

    def views(self, buf) -> dict:
        return {name: np.ndarray(shape, np.dtype(dt), buffer=buf, offset=off)
                for name, shape, dt, off in self.entries}


class SharedBlock:
    """A zero-filled block of ``size`` bytes that another process can map by ``path``; ``path=None`` -> private.

    The block has no name in any file system: an anonymous memory file (``memfd_create``; where the kernel lacks it,
    a file in /dev/shm removed the moment it is made), known by its descriptor :attr:`fd`. Its ``path`` is
    ``/proc/self/fd/FD``: a worker started with that descriptor kept (``Popen(pass_fds=...)``, the same number)
    maps it by that path. So a session killed at any moment, even while a worker starts, leaves nothing behind; the
    memory goes when its last mapping does. :meth:`release` closes the creating side's descriptor once the workers
    have mapped the block."""

    def __init__(self, size: int, path: str | None = None, create: bool = True, private: bool = False):
        self.size, self.path, self.fd = size, None, None
        if private:
            self.buf = bytearray(size)
            return
        if create:
            fd = _anonymous_file()
            os.ftruncate(fd, size)
            self.fd, path = fd, f"/proc/self/fd/{fd}"
        else:
            fd = os.open(path, os.O_RDWR)
        try:
            self._mm = mmap.mmap(fd, size)
        finally:
            if not create:
                os.close(fd)
        self.path, self.buf = path, self._mm

    def release(self) -> None:
        """Close the creating side's descriptor (the mappings keep the memory): after every worker has mapped it."""
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def _anonymous_file() -> int:
    """A descriptor of a memory file with no name left on any file system (close-on-exec: a worker gets it by
    ``pass_fds`` only)."""
    if hasattr(os, "memfd_create"):
        try:
            return os.memfd_create("sonicverse-audio", os.MFD_CLOEXEC)
        except OSError:  # a kernel without it
            pass
    d = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()
    fd, path = tempfile.mkstemp(prefix="sonicverse-audio-", dir=d)
    os.unlink(path)
    return fd


class Ring:
    """SPSC float32 ring (channels, capacity) over a ``data`` view and a one-element int64 ``head`` view (frames
    written so far). Allocation-free on the write side."""

    def __init__(self, data: np.ndarray, head: np.ndarray):
        self.data, self.head = data, head
        self.capacity = data.shape[1]
        self.read_pos = int(head[0])
        self.lost = 0

    def write(self, frames: np.ndarray) -> None:
        """frames: (channels, n) or (n,) for one channel; n <= capacity."""
        n = frames.shape[-1]
        h = int(self.head[0])
        i = h % self.capacity
        k = min(n, self.capacity - i)
        self.data[:, i:i + k] = frames[..., :k]
        if k < n:
            self.data[:, : n - k] = frames[..., k:]
        self.head[0] = h + n  # publish after the samples

    def available(self) -> int:
        return int(self.head[0]) - self.read_pos

    def read(self, max_frames: int | None = None) -> np.ndarray:
        """The frames written since the last read (a copy, (channels, n)); skips ahead if overrun."""
        h = int(self.head[0])
        if h - self.read_pos > self.capacity:
            self.lost += h - self.capacity - self.read_pos
            self.read_pos = h - self.capacity
        n = h - self.read_pos if max_frames is None else min(max_frames, h - self.read_pos)
        idx = (self.read_pos + np.arange(n)) % self.capacity
        out = self.data[:, idx]
        if int(self.head[0]) - self.read_pos > self.capacity:  # overwritten while copying: drop the oldest part
            behind = int(self.head[0]) - self.capacity - self.read_pos
            self.lost += behind
            out = out[:, behind:]
            self.read_pos += behind
        self.read_pos += out.shape[1]
        return out

    def skip_to_end(self) -> None:
        self.read_pos = int(self.head[0])


class SeqLock:
    """Single writer, any number of readers; ``seq`` is a one-element int64 view, ``data`` a float64 vector."""

    def __init__(self, seq: np.ndarray, data: np.ndarray):
        self.seq, self.data = seq, data
        self.last = -1
        self._scratch = np.empty_like(data)

    def write(self, values: np.ndarray) -> None:
        s = int(self.seq[0])
        self.seq[0] = s + 1  # odd: a write is in progress
        self.data[:] = values
        self.seq[0] = s + 2

    def read_into(self, out: np.ndarray, tries: int = 8) -> int:
        """Copy the latest consistent vector into ``out``. Returns 1 if it is new since the last call, 0 if
        unchanged, -1 if no consistent copy was had in ``tries`` (``out`` then keeps its previous contents)."""
        for _ in range(tries):
            s1 = int(self.seq[0])
            if s1 & 1:
                continue
            if s1 == self.last:
                return 0
            self._scratch[:] = self.data
            if int(self.seq[0]) == s1:
                out[:] = self._scratch
                self.last = s1
                return 1
        return -1
