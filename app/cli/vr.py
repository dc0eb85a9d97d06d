"""`sonicverse vr` (the VR application) and `sonicverse bench vr`."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from app.cli import args as A
from sonicverse_core.errors import ConfigError


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and \
        os.environ.get("QT_QPA_PLATFORM", "") not in ("offscreen", "minimal")


def headset_present() -> bool:
    """OpenVR's cheap check (no runtime start); its client library's complaint about a missing runtime, printed
    straight to file descriptor 2, is kept out of the auto choice's output."""
    try:
        import openvr
    except ImportError:
        return False
    from app.vr.openvr_backend import runtime_chatter

    try:
        with runtime_chatter([]):
            return bool(openvr.isHmdPresent())
    except Exception:  # noqa: BLE001 - no runtime library: no headset
        return False


def choose_backend(name: str) -> str:
    """'auto': OpenVR when a headset is there, the desktop window when a display is there, else headless."""
    if name != "auto":
        return name
    if headset_present():
        return "openvr"
    return "desktop" if has_display() else "headless"


def cmd_vr(a) -> int:
    from app.vr.frame import Recording
    from app.vr.session import SessionConfig, VRSession

    backend_name = choose_backend(a.backend)
    recording = None
    scene, seed, robots = a.scene, a.seed, a.robots
    if a.replay:
        if backend_name != "headless":
            raise ConfigError("--replay runs in the headless backend (add --backend headless)")
        recording = Recording.load(a.replay)
        scene = a.scene or recording.meta.get("scene")
        seed = recording.meta.get("seed", seed)
        robots = recording.meta.get("robots", robots)
    task = None
    task_name, agent = a.task, a.agent
    if recording is not None and task_name is None:
        task_name, agent = recording.meta.get("task"), recording.meta.get("agent")
    views = not a.audio_only
    if task_name:
        from app.tasks.in_the_loop import OrientationTrials, make_frame_task

        task = make_frame_task(task_name, agent, seed, trials=a.trials, mode=a.mode)
        if isinstance(task, OrientationTrials):  # audio only: nothing visual is loaded, no robot
            views, robots = False, 0
    headless = backend_name == "headless"
    frames = a.frames if a.frames is not None else \
        ((180 if task is None else 90 * int(a.rate or 90)) if headless and not a.replay else None)
    out = a.out or ("out/vr" if headless else None)
    cfg = SessionConfig(scene=scene or "builtin:apartment", views=views,
                        audio=a.audio or ("offline" if headless else "live"), audio_device=a.audio_device,
                        robots=robots, msaa=a.msaa, cull_rooms=a.cull_rooms, seed=seed, hrtf=a.hrtf == "on",
                        reverb=a.reverb == "on",
                        write_frames=a.write_frames if a.write_frames is not None else (10 if headless else 0))
    if not a.overwrite and (not headless or cfg.audio == "live"):  # a person's session: it cannot be played again
        earlier = [Path(out) / n for n in ("stats.json", "input.svrec")] if out else []
        taken = [p for p in earlier + ([Path(a.record)] if a.record else []) if p.exists()]
        if taken:
            raise ConfigError(f"{taken[0]} holds an earlier session (a person's session cannot be played again): "
                              "give another --out / --record, or --overwrite to replace it")
    from app.vr import open_backend

    backend = open_backend(backend_name, a.size, a.rate, a.realtime, recording)
    with VRSession(cfg, backend, task=task) as s:
        if task is not None:
            s.recording.meta.update(task=task.name, agent=getattr(task, "agent_name", None))
        if not a.json:
            why = " (no VR headset, no display)" if a.backend == "auto" and headless else ""
            print(f"sonicverse vr: {backend_name} backend{why}, {cfg.scene}, eyes {backend.width}x{backend.height} "
                  f"at {backend.target_hz:g} Hz" + (", audio only" if a.audio_only else ""), file=sys.stderr)
        if a.record and a.record.endswith(".svrec"):
            s.recording.stream_to(a.record)
        try:
            s.run(frames=frames, out=out)
        finally:  # Ctrl-C, SIGTERM or an error: finish every file first (what ran is kept)
            if a.record:
                s.recording.save(a.record)
            written = s.save(out) if out else []
            s.recording.close()
        summary = s.summary()
    keys = ("frames", "missed_frames", "frame_ms_p50", "frame_ms_p99", "target_hz")
    if a.json:
        print(json.dumps({**{k: summary[k] for k in keys}, **{k: v for k, v in summary.items() if k not in keys},
                          "out": out, "files": written}))
    else:
        print(" ".join(f"{k}={summary[k]}" for k in keys) + (f"; wrote {len(written)} files to {out}/" if out else ""))
        for e in summary["events"]:
            print(f"  {e}", file=sys.stderr)
    return 0


def cmd_bench_vr(a) -> int:
    from app.bench.vr import bench_vr, live_audio_task

    if a.task:
        if a.audio_seconds <= 0:
            raise ConfigError("--task runs the live-audio part: give --audio-seconds > 0")
        print(json.dumps(live_audio_task(a.task, a.audio_seconds, a.scene, a.agent, a.seed, a.jack_period)))
        return 0

    try:
        levels = [int(x) for x in a.culling_levels.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--culling-levels takes comma-separated integers, got '{a.culling_levels}'") from None
    if any(not 0 <= lv <= 4 for lv in levels):
        raise ConfigError("--culling-levels must be within 0-4 (each level x4 triangles)")
    print(json.dumps(bench_vr(a.sizes, a.frames, a.scene, a.audio_seconds,
                              a.culling_scene, levels, a.jack_period)))
    return 0


def add_vr_commands(sub, bench_sub) -> None:
    v = sub.add_parser("vr", help="the VR application (OpenVR headset, desktop window or headless)",
                       description="Stand in a scene as an audio-visual avatar: stereo views, binaural audio, a "
                       "robot that hears you. --backend auto picks OpenVR when a headset is there, the desktop "
                       "window when a display is there, otherwise a short headless session that writes stereo "
                       "frames, the binaural audio at your ears and the frame statistics to --out.")
    v.add_argument("--backend", default="auto", choices=("auto", "openvr", "desktop", "headless"),
                   help="auto: a headset if one is there, else a desktop window, else headless (default: auto)")
    v.add_argument("--scene", default=None, help="scene spec (default: builtin:apartment)")
    v.add_argument("--frames", type=A.count(1, 10**9), default=None, help="stop after N frames (headless default: 180)")
    v.add_argument("--size", default=None, type=A.argtype(A.size),
                   help="eye size WxH (default: the headset's, else 512x512)")
    v.add_argument("--rate", type=A.number(1, 1000, unit="Hz"), default=None,
                   help="target frame rate, Hz (default: headset/display, headless 90)")
    v.add_argument("--audio", default=None, choices=("offline", "live", "none"),
                   help="offline: rendered by the frame clock (headless default); live: sound card / JACK")
    v.add_argument("--audio-device", default=None, help="PortAudio device name or index for --audio live")
    v.add_argument("--audio-only", action="store_true", help="no views at all (tracking and audio go on)")
    v.add_argument("--robots", type=int, default=1, choices=(0, 1), help="robots in the scene (default: 1)")
    v.add_argument("--msaa", action="store_true", help="4x multisampling (slower on a CPU)")
    v.add_argument("--cull-rooms", default="auto", choices=["auto", "on", "off"],
                   help="load and draw only the rooms the eye may see (auto: in scenes of 250k+ triangles; below, "
                        "one merged mesh draws as fast on a CPU: see bench vr)")
    v.add_argument("--realtime", action="store_true", help="headless: pace frames to the wall clock")
    v.add_argument("--record", default=None, metavar="FILE", type=A.out_file(".svrec", ".npz"),
                   help="record the input for replay (written as it runs: .svrec; .npz at the end)")
    v.add_argument("--replay", default=None, metavar="FILE", type=A.in_file(".svrec", ".npz"),
                   help="replay a recorded input (headless)")
    v.add_argument("--write-frames", type=A.count(0, 10**6), default=None, metavar="N",
                   help="save every N-th stereo frame as PNG (headless default: 10; 0: none)")
    v.add_argument("--out", default=None, type=A.out_dir, help="output folder (headless default: out/vr)")
    v.add_argument("--seed", type=A.seed, default=0, help="seed of the robot's start and the scripted walk")
    v.add_argument("--task", default=None, metavar="TASK",
                   help="a human-robot task with the user as the person: speaker-following, voice-retrieval, "
                        "orientation-training (headless: a simulated user; ends when the task does)")
    v.add_argument("--agent", default=None, help="the robot's agent for --task (default: the task's first)")
    v.add_argument("--trials", type=A.count(1, 10_000), default=10, help="orientation-training trials (default: 10)")
    v.add_argument("--mode", default="turn", choices=("turn", "walk"), help="orientation-training trials' kind")
    v.add_argument("--hrtf", default="on", choices=("on", "off"),
                   help="off: an interaural time and level panner instead of the HRTF (default: on)")
    v.add_argument("--reverb", default="on", choices=("on", "off"),
                   help="off: no early reflections and no late reverb (default: on)")
    v.add_argument("--overwrite", action="store_true",
                   help="replace the files of an earlier session in --out (or --record's file); without it a session "
                   "with a person (desktop, openvr, live audio) is refused where one would be replaced")
    v.add_argument("--json", action="store_true", help="print one JSON object with the frame statistics")
    v.set_defaults(func=cmd_vr)

    b = bench_sub.add_parser("vr", help="stereo frames/s of the headless loop; audio xruns while it runs flat out")
    b.add_argument("--sizes", default="512x512,1080x1200",
                   type=A.argtype(lambda t: [A.size(x) for x in t.split(",")]), help="eye sizes (default: %(default)s)")
    b.add_argument("--frames", type=A.count(10, 100_000), default=60, help="frames per size (default: %(default)s)")
    b.add_argument("--scene", default="builtin:apartment", help="scene spec (default: %(default)s)")
    b.add_argument("--culling-scene", default="builtin:apartment?seed=1", help="scene of the room-culling rows")
    b.add_argument("--culling-levels", default="0,3",
                   help="subdivision levels of the culling scene (each x4 triangles; default: %(default)s)")
    b.add_argument("--audio-seconds", type=A.number(0, 3600, unit="s"), default=20.0,
                   help="seconds of the live-audio run on a private JACK dummy server (0: skip)")
    b.add_argument("--task", default=None, metavar="TASK",
                   help="only the live-audio run, with this human-robot task in the loop (paced at 90 Hz; "
                        "speaker-following, voice-retrieval, orientation-training)")
    b.add_argument("--agent", default=None, help="the robot's agent for --task (default: the task's first)")
    b.add_argument("--seed", type=A.seed, default=0, help="seed of the task (default: 0)")
    b.add_argument("--jack-period", type=int, default=256, choices=(256, 512, 1024),
                   help="frames per cycle of the private JACK server (the engine renders 256-frame blocks; "
                        "default: %(default)s)")
    b.add_argument("--json", action="store_true", help="(always JSON)")
    b.set_defaults(func=cmd_bench_vr)
