"""A JACK server with the dummy backend: a real clocked audio device without a sound card (tests, benchmarks).

Started with ``jackd -n NAME -d dummy`` and stopped by its PID with SIGTERM (a clean shutdown that leaves no stale
entry in JACK's server registry in /dev/shm), SIGKILL only if that hangs. It gets SIGTERM too when the thread that
started it goes away without stopping it (a test run or a benchmark killed: util-linux's ``setpriv --pdeathsig``),
so no real-time server outlives its user. Point PortAudio at it with ``JACK_DEFAULT_SERVER=NAME``.
"""
from __future__ import annotations

import ctypes
import shutil
import subprocess

from app.audio_rt.sched import NICE_SERVER, favour_process_threads
from sonicverse_core.errors import DependencyError, DeviceError


class JackServer:
    def __init__(self, name: str, rate: int = 48000, period: int = 256, playback: int = 2, capture: int = 2,
                 realtime: bool = True):
        """``realtime`` False: the server runs time-shared (``jackd --no-realtime``), as it does on a machine that
        refuses it real time; its time-shared threads then get nice -20 where allowed. :attr:`scheduling` says what
        its threads run at."""
        from app.audio_rt.sched import nice_roles

        nice_roles()  # a bad SONICVERSE_RT_NICE: a ConfigError before any server starts
        self.name = name
        self.scheduling = None
        exe = shutil.which("jackd")
        if exe is None:
            raise DependencyError("jackd not found: install the Debian package jackd2 (scripts/install-system.sh)")
        guard = shutil.which("setpriv")  # util-linux (essential on Debian)
        self.cmd = ([guard, "--pdeathsig", "TERM"] if guard else []) + [
            exe, "-n", name, *([] if realtime else ["--no-realtime"]), "-d", "dummy", "-r", str(rate), "-p",
            str(period), "-P", str(playback), "-C", str(capture)]
        self.proc = None
        sweep_stale_futexes()
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        w = subprocess.run(["jack_wait", "-s", self.name, "-w", "-t", "20"], capture_output=True, text=True)
        if w.returncode != 0 or self.proc.poll() is not None:
            err = self.proc.stderr.read() if self.proc.poll() is not None else w.stdout
            self.stop()
            raise DeviceError(f"JACK server '{self.name}' did not start: {err.strip()[-300:]}")
        self.scheduling = favour_process_threads(self.proc.pid, NICE_SERVER)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        if self.proc is not None:
            self._remove_client_futexes()
        self.proc = None

    def _remove_client_futexes(self) -> None:
        """Remove what the stopped server left in /dev/shm of its clients' wake-up words. jack2 on Linux keeps one
        per client (``jack_sem.UID_SERVER_CLIENT``, its ``JackLinuxFutex``) and removes it when the client closes
        while the server runs; a server stopped under a client (a device that vanishes, a test that stops it) leaves
        them, a dozen bytes each, for good. They are this server's alone (its name), and it has exited."""
        import glob
        import os

        for path in glob.glob(f"/dev/shm/jack_sem.{os.getuid()}_{glob.escape(self.name)}_*"):
            try:
                os.unlink(path)
            except OSError:  # gone already, or not ours to remove
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def sweep_stale_futexes() -> list[str]:
    """Remove the client futex files (see :meth:`JackServer._remove_client_futexes`) of servers named by our
    convention, ``sv-KIND-PID[-N]``, whose owner PID is gone: what a session killed with SIGKILL left (its server
    gets SIGTERM by pdeathsig, under its clients). Another live process's, and any other server's, are left alone.
    Returns the paths removed."""
    import glob
    import os
    import re

    gone = []
    for path in glob.glob(f"/dev/shm/jack_sem.{os.getuid()}_sv-*"):
        m = re.fullmatch(rf"jack_sem\.{os.getuid()}_sv-[a-z]+-(\d+)(?:-\d+)?_.+", os.path.basename(path))
        if m is None:
            continue
        try:
            os.kill(int(m.group(1)), 0)
            continue  # its owner lives (or the PID was reused: leave it)
        except ProcessLookupError:
            pass
        except (PermissionError, OverflowError):
            continue
        try:
            os.unlink(path)
            gone.append(path)
        except OSError:
            pass
    return gone


_client_name = None  # PortAudio keeps the pointer: the bytes must outlive the stream


def name_jack_client(name: str) -> None:
    """Name the JACK client of the streams this process opens.

    PortAudio takes the name only when it initialises, which ``import sounddevice`` does. So the name is set before
    that import where this process has not made it yet (an audio worker: a fresh interpreter), through the library
    sounddevice will load. Where it has, PortAudio is re-initialised to take the name, which closes every stream the
    process has open, so that happens once per process: a second engine of a process (``mode="thread"``) keeps the
    first's name and its stream (it used to stop the first engine's stream, which then never called back again)."""
    global _client_name
    import sys

    if _client_name is not None:  # named already: renaming would close the streams it has open
        return
    want = name.encode()[:60]
    if "sounddevice" not in sys.modules:
        from ctypes.util import find_library

        found = find_library("portaudio")  # what sounddevice loads first on POSIX
        if found is not None and _set_client_name(found, want):
            import sounddevice as sd

            if sd._libname == found:
                return  # initialised once, with the name
    import sounddevice as sd

    if _set_client_name(sd._libname, want):
        sd._terminate()
        sd._initialize()


def _set_client_name(libname: str, name: bytes) -> bool:
    """``PaJack_SetClientName`` in the PortAudio library ``libname`` (False: one without JACK support)."""
    global _client_name
    try:
        lib = ctypes.CDLL(libname)
        fn = lib.PaJack_SetClientName
    except (OSError, AttributeError):
        return False
    _client_name = name  # before the call: PortAudio keeps the pointer
    fn(ctypes.c_char_p(_client_name))
    return True


def _jack(*args: str) -> str:
    exe = shutil.which(args[0])
    if exe is None:
        raise DependencyError(f"'{args[0]}' not found: install the Debian package jackd2 (scripts/install-system.sh)")
    p = subprocess.run([exe, *args[1:]], capture_output=True, text=True, timeout=10)
    if p.returncode != 0 and args[0] != "jack_disconnect":
        raise DeviceError(f"{' '.join(args)} failed: {(p.stderr or p.stdout).strip().splitlines()[-1:]}")
    return p.stdout


def jack_buffer_size() -> int:
    """The running JACK server's frames per cycle, as it reports them (the server JACK_DEFAULT_SERVER names)."""
    return int(_jack("jack_bufsize").split("=")[-1].split()[0])


def jack_connections() -> dict[str, list[str]]:
    """port -> ports it is connected to (from jack_lsp -c)."""
    out, cur = {}, None
    for line in _jack("jack_lsp", "-c").splitlines():
        if line.startswith((" ", "\t")):
            out.setdefault(cur, []).append(line.strip())
        elif line.strip():
            cur = line.strip()
            out.setdefault(cur, [])
    return out


def connect_loopback(client: str) -> tuple[str, str]:
    """Wire ``client``'s first output to its first input, and nothing else into that input."""
    conns = jack_connections()
    outs = sorted(p for p in conns if p.startswith(client + ":out"))
    ins = sorted(p for p in conns if p.startswith(client + ":in"))
    if not outs or not ins:
        raise DeviceError(f"JACK client '{client}' has no ports to loop back (ports: {sorted(conns)[:8]})")
    for port in ins:
        for other in conns[port]:
            _jack("jack_disconnect", other, port)
    _jack("jack_connect", outs[0], ins[0])
    return outs[0], ins[0]
