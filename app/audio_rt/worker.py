"""The audio side's main: check the devices, build the renderer, warm it up, open the duplex stream, supervise it.

Runs as the target of a spawned process (mode 'process') or of a thread (mode 'thread'). It talks to the main side
through a pipe (start result, stop, device lost) and shares everything per-block through the shared block.

When the device disappears (a JACK server stopped, a USB headset unplugged), PortAudio's stream stops calling back
and can neither be stopped nor closed safely: Pa_StopStream waits on a thread that is gone and Pa_CloseStream
asserts (measured with JACK: the process aborts). So the worker reports the loss and its process exits at once
without touching the stream; the application is in another process and stays up, and a new stream opens in a new
process. In thread mode the dead stream is abandoned instead.
"""
from __future__ import annotations

import gc
import os
import subprocess
import time

import numpy as np

from app.audio_rt import config as C
from app.audio_rt.sched import NICE_ROBOTS, NICE_SUPERVISOR, favour_this_thread


def stall_seconds(cfg) -> float:
    """How long the stream may go without a callback before the supervisor calls the device lost."""
    return max(0.5, 50 * cfg.block / cfg.sample_rate)


def run(conn, cfg, scene_setup, shm_path: str | None, shared_buf=None, role: str = "all") -> None:
    """Worker entry point (``shared_buf`` is given in thread mode, ``shm_path`` in process mode); ``role``: 'all'
    (the callback renders the user and the robots) or 'user' (the robots render in :func:`run_robots`)."""
    from app.audio_rt.core import AudioCore, attach
    from sonicverse_core.errors import DeviceError, SonicverseError

    in_thread = shared_buf is not None
    try:
        sh, pose_layout = attach(cfg, scene_setup, shared_buf, shm_path)
        sh.tele[C.PID] = os.getpid()
    except Exception as exc:  # noqa: BLE001
        conn.send(("error", "ConfigError", f"audio worker could not start: {exc}"))
        return
    try:
        import sounddevice as sd

        from app.audio_rt.devices import check
        from app.audio_rt.jack import name_jack_client

        client = f"sonicverse-{os.getpid()}"
        name_jack_client(client)

        out_dev, in_dev = check(cfg)
        if role == "user":  # the devices are there: the engine starts the robots' worker, then says go
            conn.send(("checked",))
            if not _go(conn):
                return
        t0 = time.perf_counter()
        core = AudioCore(cfg, scene_setup, sh, pose_layout, role=role)
        core.warm_up()
        warm = time.perf_counter() - t0
        channels = (cfg.mic_channel + 1, 2) if in_dev is not None else 2
        device = (in_dev["index"], out_dev["index"]) if in_dev is not None else out_dev["index"]
        kind = sd.Stream if in_dev is not None else sd.OutputStream
        cb = core.callback if in_dev is not None else (lambda o, f, t, s: core.callback(core.zero_in, o, f, t, s))
        stream = kind(device=device, samplerate=cfg.sample_rate, blocksize=cfg.block, channels=channels,
                      dtype="float32", latency=cfg.latency, callback=cb)
        lat = stream.latency if isinstance(stream.latency, tuple) else (0.0, stream.latency)
        sh.telef[C.LAT_IN], sh.telef[C.LAT_OUT] = lat
        sh.telef[C.SAMPLE_RATE] = stream.samplerate
        if not in_thread:  # nothing in this process allocates cycles from now on: no collector pauses
            gc.collect()
            gc.freeze()
            gc.disable()
        from app.audio_rt.qos import LatencyRequest

        qos = LatencyRequest(0)  # held until this process ends (or the stream stops, in thread mode)
        sh.tele[C.CB_POLICY] = -1  # the first callback writes its thread's scheduling
        stream.start()
        sh.tele[C.STATE] = C.RUNNING
        # JACK calls back once a cycle and PortAudio splits the cycle into blocks, flagging each block of a late cycle:
        # the telemetry counts xruns per cycle, so it needs the server's frames per cycle (None: not a JACK device)
        host_period = _jack_period() if "JACK" in out_dev["hostapi"] else None
    except SonicverseError as exc:
        sh.tele[C.STATE] = C.FAILED
        conn.send(("error", type(exc).__name__, str(exc)))
        return
    except Exception as exc:  # noqa: BLE001 - PortAudioError and anything else: report, never hang the caller
        sh.tele[C.STATE] = C.FAILED
        conn.send(("error", DeviceError.__name__, f"cannot open the audio stream: {str(exc).splitlines()[0]}"))
        return
    # the supervisor (this thread) takes its real-time priority before the news goes out, so that the news says
    # whether this machine allows one (the callback's thread takes the audio server's)
    sched = _realtime_supervisor() if not in_thread else "in the caller's thread"
    conn.send(("ready", {"output_device": out_dev["name"], "input_device": in_dev["name"] if in_dev else None,
                         "hostapi": out_dev["hostapi"], "sample_rate": stream.samplerate, "block": cfg.block,
                         "latency_in_s": lat[0], "latency_out_s": lat[1], "warmup_s": round(warm, 3),
                         "subsystems": core.r.subsystems, "doors": core.doors, "mode": cfg.mode,
                         "pid": os.getpid(), "jack_client": client if "JACK" in out_dev["hostapi"] else None,
                         "cpu_latency_request": "held" if qos.held else f"not held ({qos.why})",
                         "supervisor_scheduling": sched, "host_period": host_period}))
    if not in_thread:
        import sys

        sys.setswitchinterval(0.0005)  # the callback gets the GIL back within 0.5 ms after a GIL-free kernel
    last_count, last_change = -1, time.monotonic()
    stall = stall_seconds(cfg)
    while True:
        if _stop_asked(conn, 0.05):
            stream.stop()
            stream.close()
            qos.release()
            sh.tele[C.STATE] = C.STOPPED
            _send(conn, ("stopped",))
            return
        count = int(sh.tele[C.CALLBACKS])
        now = time.monotonic()
        if count != last_count:
            last_count, last_change = count, now
        why = None
        if not stream.active:
            why = "the audio device stopped the stream (device disconnected or audio server shut down)"
        elif now - last_change > stall:
            why = f"the audio device stopped calling back for {now - last_change:.1f} s (device gone or stalled)"
        if why is not None:
            sh.tele[C.STATE] = C.LOST
            conn.send(("lost", why))
            if in_thread:
                return  # the stream is abandoned: stopping or closing it would hang or abort
            os._exit(3)



def run_robots(conn, cfg, scene_setup, shm_path: str) -> None:
    """The robot listeners' process: renders what the robots hear, block by block, one block behind the stream.

    The stream's callback renders the user's ears only (the deadline that matters) and writes each microphone block
    to its ring; this process follows that ring (or the callback's frame counter when there is no microphone),
    reads the same pose frames, and writes the robots' rings. Its own interpreter and GIL: its DSP never delays the
    callback, and a slow robot block costs robot latency, never an xrun. Runs at a real-time priority below the
    callback's and the supervisor's where allowed."""
    from app.audio_rt.core import AudioCore, attach
    from app.audio_rt.shared import Ring

    try:
        sh, pose_layout = attach(cfg, scene_setup, shm_path=shm_path)
        core = AudioCore(cfg, scene_setup, sh, pose_layout, role="robots")
        core.warm_up()
    except Exception as exc:  # noqa: BLE001
        from sonicverse_core.errors import SonicverseError

        conn.send(("error", type(exc).__name__ if isinstance(exc, SonicverseError) else "ConfigError",
                   f"the robot listeners' audio process could not start: {exc}"))
        return
    mic = Ring(sh.mic.data, sh.mic.head) if cfg.mic else None  # this process's own reader of the mic ring
    if mic is not None:
        mic.read_pos = 0
    B = cfg.block
    gc.collect()
    gc.freeze()
    gc.disable()
    conn.send(("ready", {"pid": os.getpid()}))
    favour_this_thread(3, NICE_ROBOTS, "robots")
    done = 0  # stream frames rendered: the robots' rings are indexed by stream frame, like the user's and the mic's
    while True:
        if _stop_asked(conn, 0):
            _send(conn, ("stopped",))
            return
        frames = int(sh.tele[C.FRAMES])
        if frames - done < B:
            time.sleep(0.001)
            continue
        if frames - done > sh.mic.capacity // 2:  # fell far behind (the machine stalled): silence, then the present
            gap = frames - done
            sh.tele[C.ROBOT_SKIPPED] += gap // B
            for ring in sh.ears[1:]:
                ring.write(np.zeros((2, min(gap, ring.capacity)), np.float32))
                ring.head[0] = frames
            done = frames
            if mic is not None:
                mic.read_pos = done
            continue
        try:
            block = None
            if mic is not None:
                block = mic.read(B)[0]  # written before the counter moved: always a whole block
            core.render_robots(block)
        except Exception as exc:  # noqa: BLE001 - reported like a callback error; the robots hear silence
            for ring in sh.ears[1:]:
                ring.write(np.zeros((2, B), np.float32))
            sh.set_error(f"robot listeners: {type(exc).__name__}: {exc}")  # the text before the count (see core)
            sh.tele[C.ERRORS] += 1
        done += B
        sh.tele[C.ROBOT_BLOCKS] += 1


def _go(conn) -> bool:
    """Wait for the engine's go (False: it stopped instead, or went away)."""
    try:
        return conn.recv()[0] == "go"
    except (EOFError, OSError):
        return False


def _stop_asked(conn, timeout: float) -> bool:
    """True when the application asks to stop within ``timeout`` s, or went away (then stop quietly)."""
    try:
        return conn.poll(timeout) and conn.recv()[0] == "stop"
    except (EOFError, OSError):
        return True


def _send(conn, msg) -> None:
    try:
        conn.send(msg)
    except OSError:  # the application went away
        pass


def _jack_period() -> int | None:
    """The JACK server's frames per cycle at the stream's start; None when jack_bufsize cannot say (the telemetry
    then counts each flagged block as an xrun and says so: ``cycle_blocks`` None)."""
    from app.audio_rt.jack import jack_buffer_size

    try:
        return jack_buffer_size()
    except (SonicverseError, OSError, ValueError, subprocess.SubprocessError):
        return None


def _realtime_supervisor() -> str:
    """Run this (supervising) thread at a real-time priority below the audio callback's, where allowed (else at a
    time-shared priority below the callback's fallback): it holds the GIL for microseconds every 50 ms, and a thread
    preempted while holding it would stall the callback (priority inversion) when the machine is loaded."""
    return favour_this_thread(4, NICE_SUPERVISOR, "supervisor")


def main() -> None:
    """Process entry: ``python -c 'import app.audio_rt.worker as w; w.main()' FD`` (FD: a socket to the engine)."""
    import sys
    from multiprocessing.connection import Connection

    conn = Connection(int(sys.argv[1]))
    cfg, scene_setup, path, role = conn.recv()
    if role == "robots":
        run_robots(conn, cfg, scene_setup, path)
    else:
        run(conn, cfg, scene_setup, path, role=role)
