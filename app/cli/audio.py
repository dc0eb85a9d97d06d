"""`sonicverse audio ...`: devices, loopback-test, live."""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from app.cli import args as A
from sonicverse_core.errors import ConfigError, SonicverseError


def _device(text):
    if text is None:
        return None
    return int(text) if text.isdigit() else text


def cmd_devices(a) -> int:
    from app.audio_rt.devices import list_devices

    devs = list_devices()
    if a.json:
        print(json.dumps({"devices": devs}))
    elif not devs:
        print("no audio devices (no sound card, and no JACK server running: start one with "
              "'jackd -d dummy -r 48000 -p 256 &' for a virtual device)")
    else:
        for d in devs:
            print(f"[{d['index']}] {d['name']} ({d['hostapi']}): {d['inputs']} in / {d['outputs']} out, "
                  f"{d['default_sample_rate']:.0f} Hz, {d['default_low_latency_ms']} ms")
    return 0


def cmd_loopback(a) -> int:
    from app.audio_rt.loopback import loopback_test

    res = loopback_test(a.seconds, a.sources, None if a.scene == "none" else a.scene, a.mode, a.load, a.robots,
                        _device(a.device), a.sample_rate, a.block, a.view,
                        progress=lambda e: print(f"sonicverse: {e}", file=sys.stderr), door_every=a.door_every)
    if a.json:
        print(json.dumps(res))
    else:
        print(f"round trip {res['round_trip_ms']} ms ({res['round_trip_periods']} periods of {res['block_ms']} ms), "
              f"{res['xruns']} xruns in {res['callbacks']} callbacks, callback p99 {res['callback_p99_ms']} ms")
    return 0


class _Keys:
    """Head pose from the terminal: w/s step forward/back, a/d turn, q quits (when stdin is a terminal)."""

    def __init__(self):
        self.tty = sys.stdin.isatty()
        if self.tty:
            import termios
            import tty

            self._old = termios.tcgetattr(sys.stdin)
            tty.setcbreak(sys.stdin.fileno())

    def read(self) -> str:
        if not self.tty:
            return ""
        import select

        keys = ""
        while select.select([sys.stdin], [], [], 0)[0]:
            keys += sys.stdin.read(1)
        return keys

    def close(self):
        if self.tty:
            import termios

            termios.tcsetattr(sys.stdin, termios.TCSADRAIN, self._old)


def cmd_live(a) -> int:
    """Microphone + scene to headphones; head pose from the keyboard (w/s/a/d, q to quit)."""
    from app.audio_rt.config import AudioConfig, AudioScene
    from app.audio_rt.engine import AudioEngine
    from app.audio_rt.loopback import random_sources

    if a.record and os.path.exists(a.record) and not a.overwrite:  # a person's take: it cannot be recorded again
        raise ConfigError(f"{a.record} holds an earlier recording: give another --record, or --overwrite to "
                          "replace it")
    spec = None if a.scene == "none" else a.scene
    srcs, head = random_sources(spec, a.sources, a.seed, gain=0.1)
    cfg = AudioConfig(device=_device(a.device), input_device=_device(a.input_device), sample_rate=a.sample_rate,
                      block=a.block, sidetone=a.sidetone, mic=not a.no_mic)
    eng = AudioEngine(cfg, AudioScene(spec, sources=srcs, head=head))
    info = eng.start()
    if not a.json:
        print(f"live on '{info['output_device']}' ({info['hostapi']}), {info['sample_rate']:.0f} Hz / {a.block}; "
              f"w/s: step, a/d: turn, q: quit", file=sys.stderr)
    keys = _Keys()
    x, y, z, yaw = head[0], head[1], head[2], head[3]
    recorded = []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < a.seconds:
            k = keys.read()
            if "q" in k:
                break
            yaw += 10.0 * (k.count("a") - k.count("d"))
            step = 0.1 * (k.count("w") - k.count("s"))
            x, y = x + step * np.cos(np.radians(yaw)), y + step * np.sin(np.radians(yaw))
            eng.set_poses((x, y, z, yaw, 0.0))
            time.sleep(1 / 90)  # the frame clock of a headless session
            if a.record:
                recorded.append(eng.read_ears(0))
            for e in eng.poll():
                print(f"sonicverse: {e}", file=sys.stderr)
            if eng.state == "lost":
                if not a.reopen:
                    break
                try:
                    eng.reopen()
                except SonicverseError as exc:  # the device is still gone: stop, keeping what was recorded
                    print(f"sonicverse: {exc}", file=sys.stderr)
                    break
    finally:  # Ctrl-C, SIGTERM or an error too: what was recorded is written
        keys.close()
        tele = eng.telemetry()
        eng.stop()
        if a.record and recorded:
            import soundfile as sf

            from sonicverse_core.storage import atomic_write

            with atomic_write(a.record) as fh:
                sf.write(fh, np.concatenate(recorded, axis=1).T, a.sample_rate, subtype="FLOAT", format="WAV")
    res = {"device": info["output_device"], "seconds": round(time.monotonic() - t0, 2), **tele}
    print(json.dumps(res) if a.json else f"{tele['callbacks']} callbacks, {tele['xruns']} xruns, "
          f"callback p99 {tele['callback_ms']['p99']} ms")
    return 0


def add_commands(sub) -> None:
    au = sub.add_parser("audio", help="real-time audio: devices, loopback test, live session",
                        description="Real-time audio through PortAudio (a sound card, or a JACK server).")
    s = au.add_subparsers(dest="audio_command", metavar="SUBCOMMAND", required=True)
    d = s.add_parser("devices", help="list audio devices")
    d.add_argument("--json", action="store_true", help="print one JSON object")
    d.set_defaults(func=cmd_devices)

    def stream_args(p):
        p.add_argument("--device", help="output (and input) device: name or index (default: the default)")
        p.add_argument("--sample-rate", type=A.count(8000, 192000), default=48000,
                       help="stream sample rate, Hz (default: %(default)s)")
        p.add_argument("--block", type=A.count(16, 8192), default=256, help="frames per callback (default: %(default)s)")
        p.add_argument("--json", action="store_true", help="print one JSON object")

    lb = s.add_parser("loopback-test", help="round trip, xruns and callback timing with output wired to input",
                      description="Open the duplex stream with a scene, wire its output to its input (JACK: "
                      "automatically; otherwise a cable), and measure round-trip latency by correlation, xruns "
                      "and callback durations while a frame loop hands poses at frame rate.")
    lb.add_argument("--seconds", type=A.number(1, 24 * 3600, unit="s"), default=10.0,
                    help="length of the test, s (default: %(default)s)")
    lb.add_argument("--sources", type=A.count(0, 1024), default=16, help="scene sources besides the microphone")
    lb.add_argument("--robots", type=A.count(0, 8), default=1, help="robot listeners hearing the microphone")
    lb.add_argument("--scene", default="builtin:apartment", help="scene spec, or 'none' for free field")
    lb.add_argument("--mode", default="process", choices=["process", "thread"],
                    help="DSP in its own process (default) or in a thread of this one")
    lb.add_argument("--load", default="none", choices=["none", "frames"],
                    help="'frames': the frame loop renders stereo views as fast as it can meanwhile")
    lb.add_argument("--view", type=A.count(16, 4096), default=512, help="eye resolution with --load frames")
    lb.add_argument("--door-every", type=A.number(0.05, 3600, unit="s"), default=None, metavar="S",
                    help="every S seconds a door of the scene (each in turn) opens or shuts, as a VR user's trigger")
    stream_args(lb)
    lb.set_defaults(func=cmd_loopback)

    lv = s.add_parser("live", help="microphone + scene to headphones, head pose from the keyboard",
                      description="Stream the microphone into the scene at the avatar's mouth and the scene to "
                      "the headphones; w/s step, a/d turn, q quits.")
    lv.add_argument("--scene", default="builtin:apartment", help="scene spec, or 'none' (default: %(default)s)")
    lv.add_argument("--sources", type=A.count(0, 256), default=4, help="sound-bank sources placed at random "
                    "(default: %(default)s)")
    lv.add_argument("--seconds", type=A.number(0, 24 * 3600, lo_open=True, unit="s"), default=3600.0,
                    help="stop after this long, s (default: %(default)s)")
    lv.add_argument("--input-device", help="microphone device (default: --device)")
    lv.add_argument("--sidetone", type=A.number(0, 4), default=0.0, help="hear your own voice in the scene (gain)")
    lv.add_argument("--no-mic", action="store_true", help="output only")
    lv.add_argument("--record", type=A.out_file(".wav"), help="write what reached the headphones to this WAV file "
                    "(also when the session ends by Ctrl-C or an error)")
    lv.add_argument("--overwrite", action="store_true", help="replace --record's file if it exists (else refused)")
    lv.add_argument("--reopen", action="store_true", help="reopen the stream when the device comes back")
    lv.add_argument("--seed", type=A.seed, default=0, help="seed of the sources' placement (default: 0)")
    stream_args(lv)
    lv.set_defaults(func=cmd_live)
