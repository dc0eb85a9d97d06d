"""Keep the CPUs out of deep idle states while the stream runs (Linux PM QoS, ``/dev/cpu_dma_latency``).

A CPU that sleeps deeply between callbacks wakes late; in a virtual machine a halted virtual CPU is descheduled by
the host and wakes later still. Writing a latency bound of 0 us to ``/dev/cpu_dma_latency`` and keeping the file
open asks the kernel to stay in shallow idle states (and a KVM guest to halt-poll) until the file is closed, which
happens by itself when the process ends. This is what cyclictest and real-time audio set-ups do. The device is
root-only on most systems: elsewhere the request is skipped and the reason is reported, never raised. It matters on
machines with deep C-states (a desktop VR PC); on the VMs here the kernel has no cpuidle driver (``none``: idle is a
plain HLT), so the request changes nothing there and the benchmarks in README.md do not depend on it.
"""
from __future__ import annotations

import os
import struct

PATH = "/dev/cpu_dma_latency"


class LatencyRequest:
    def __init__(self, microseconds: int = 0):
        self.fd, self.why = None, None
        try:
            fd = os.open(PATH, os.O_WRONLY)
        except OSError as exc:
            self.why = f"{PATH}: {exc.strerror}"
            return
        try:
            os.write(fd, struct.pack("i", int(microseconds)))
        except OSError as exc:
            os.close(fd)
            self.why = f"{PATH}: {exc.strerror}"
            return
        self.fd = fd

    @property
    def held(self) -> bool:
        return self.fd is not None

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
