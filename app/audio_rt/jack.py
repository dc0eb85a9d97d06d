"""A JACK server with the dummy backend: a real clocked audio device without a sound card (tests, benchmarks).

Started with ``jackd -n NAME -d dummy`` and stopped by its PID with SIGTERM (a clean shutdown that leaves no stale
entry in JACK's server registry in /dev/shm), SIGKILL only if that hangs. Point PortAudio at it with
``JACK_DEFAULT_SERVER=NAME``.
"""
from __future__ import annotations

import shutil
import subprocess

from sonicverse_core.errors import DependencyError, DeviceError


class JackServer:
    def __init__(self, name: str, rate: int = 48000, period: int = 256, playback: int = 2, capture: int = 2):
        self.name = name
        exe = shutil.which("jackd")
        if exe is None:
            raise DependencyError("jackd not found: install the Debian package jackd2 (scripts/install-system.sh)")
        self.cmd = [exe, "-n", name, "-d", "dummy", "-r", str(rate), "-p", str(period), "-P", str(playback),
                    "-C", str(capture)]
        self.proc = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        w = subprocess.run(["jack_wait", "-s", self.name, "-w", "-t", "20"], capture_output=True, text=True)
        if w.returncode != 0 or self.proc.poll() is not None:
            err = self.proc.stderr.read() if self.proc.poll() is not None else w.stdout
            self.stop()
            raise DeviceError(f"JACK server '{self.name}' did not start: {err.strip()[-300:]}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.proc = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
