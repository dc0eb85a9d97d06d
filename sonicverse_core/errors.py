"""The one errors module of Sonicverse.

Every mistake a user can make (an unknown scene spec, a missing file, a broken mesh, an unknown material, a bad
pose, a wrong sample rate, a device that vanishes) raises a subclass of :class:`SonicverseError`. The CLI turns any
of them into one line on stderr and exit code 2; a running session catches them and carries on.
"""
from __future__ import annotations

from contextlib import contextmanager


class SonicverseError(Exception):
    """Base class: a problem the user can fix. ``str(err)`` is one line that says what and how."""

    exit_code = 2


class SceneSpecError(SonicverseError):
    """An unknown or malformed scene spec string."""


class SceneFileError(SonicverseError):
    """A scene file or folder that is missing or cannot be read."""


class MeshError(SonicverseError):
    """Geometry that cannot be used: NaN vertices, no faces, zero volume."""


class MaterialError(SonicverseError):
    """An unknown acoustic material or a broken material mapping."""


class AssetError(SonicverseError):
    """A missing or corrupt asset (sound, HRTF, speech); the message says how to get it."""


class ConfigError(SonicverseError):
    """A setting out of its valid range (sample rate, block size, probe count...)."""


class PoseError(SonicverseError):
    """A pose or position that is not finite or lies outside what the scene allows."""


class ActionError(SonicverseError):
    """An agent action that is not finite or has the wrong shape; or a world action that cannot happen now
    (picking up an object out of reach, putting down where there is no room)."""


class DeviceError(SonicverseError):
    """An audio or VR device that does not exist, does not support a setting, or disappeared."""


class AudioCallbackError(SonicverseError):
    """An exception inside the real-time audio callback (its block played silence); reported on the main side."""


class DependencyError(SonicverseError):
    """An optional dependency that is not installed; the message names the install command."""


def require(module: str, purpose: str, install: str | None = None):
    """Import an optional module lazily, or raise :class:`DependencyError` naming the pip command."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        pkg = install or module.split(".")[0]
        raise DependencyError(
            f"{purpose} needs the Python package '{pkg}' ({exc}); install it with: .venv/bin/pip install {pkg}"
        ) from exc


class DataError(SonicverseError):
    """A data file written by Sonicverse (an input recording...) that is missing, corrupt or of another version."""


class Interrupted(SonicverseError):
    """The user or the system stopped a command (Ctrl-C, SIGTERM); files being written were finished first."""


_STOPPED: list[str] = []  # why a signal handler stopped this process (kept: the process is on its way out)
_HELD = [0]  # stop_held() depth


def stop(reason: str):
    """A signal handler's way to stop the command: note ``reason`` and raise :class:`Interrupted` wherever the main
    thread is (inside :func:`stop_held`, when the hold ends). Any ``except`` on the way may swallow that raise (one
    that catches every ``Exception`` or every ``SonicverseError``, ours or a library's); :func:`check_stopped` at the
    loops' safe points raises it again."""
    _STOPPED.append(reason)
    if _HELD[0] == 0:
        raise Interrupted(reason)


@contextmanager
def stop_held():
    """A block that a stop must not cut in two (a trial's row going into the database and the CSV): :func:`stop`
    only notes the stop while it runs, and it is raised when the outermost hold ends. Blocking the signal in the
    main thread is not enough: with other threads running, the kernel may hand the signal to one of them, and Python
    still runs its handler in the main thread at once."""
    _HELD[0] += 1
    try:
        yield
    finally:
        _HELD[0] -= 1
    if _HELD[0] == 0:
        check_stopped()


def stop_behind(exc: BaseException) -> Interrupted | None:
    """The stop that ``exc`` stands for, or None when it is an error of its own. A raise from :func:`stop` can reach
    the caller inside another exception: Python 3.11 wraps whatever is raised in a ``__set_name__`` (a dataclass's
    field while a class body runs, say while a task module is imported) in a RuntimeError, and a library may re-raise
    it as its own error. Once a stop is noted the process is on its way out, so every exception after it is that
    stop. Ctrl-C's KeyboardInterrupt wrapped the same way (an Exception caused by one, or raised while one was
    handled) is a stop too: "interrupted". None for a bare KeyboardInterrupt or SystemExit."""
    if isinstance(exc, Interrupted):
        return exc
    if not isinstance(exc, Exception):
        return None
    if _STOPPED:
        return Interrupted(_STOPPED[0])
    e, seen = exc, 0
    while e is not None and seen < 32:  # a chain, not a cycle: bounded
        if isinstance(e, KeyboardInterrupt):
            return Interrupted("interrupted")
        e, seen = e.__cause__ or e.__context__, seen + 1
    return None


@contextmanager
def stops_quiet_in_finalisers():
    """While it runs, a stop raised where Python cannot pass it on (the handler ran inside a ``__del__``, a weakref
    callback or a finaliser the collector called) prints nothing: Python would print "Exception ignored in ..." and
    a traceback, where the command promises one line. The stop stays noted, and the next :func:`check_stopped`
    raises it. Anything else raised there is printed as before."""
    import sys

    previous = sys.unraisablehook

    def hook(unraisable):
        if not (isinstance(unraisable.exc_value, Interrupted) and _STOPPED):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def check_stopped() -> None:
    """Raise :class:`Interrupted` if :func:`stop` was called in this process (the loops call it every frame)."""
    if _STOPPED:
        raise Interrupted(_STOPPED[0])


class StudyError(SonicverseError):
    """A study file that does not validate, or a study action that would lose or overwrite data (a second run of a
    participant's unfinished session, an unknown participant or session); the message says what to do instead."""
