"""The VR application's one main loop, the same for the OpenVR, desktop and headless backends.

Per frame, frame-locked: the backend's ``wait_frame()`` paces the loop (OpenVR's WaitGetPoses, the desktop's
frame clock, the headless fixed step) and returns the input; the input is recorded; one simulation step (the task,
with the frame's dt); one pose handoff to the audio side (which never waits for the loop: in live mode it runs in
its own process and interpolates the poses across its blocks); one stereo render (skipped in audio-only mode) and
one submit. Frame-to-frame intervals and the loop's own work time are kept (:class:`FrameStats`).

    with VRSession(SessionConfig(scene="builtin:apartment"), HeadlessBackend()) as s:
        s.run(frames=180)
        s.save("out/demo")
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from app.tasks.roam import FrameTask, FreeRoam
from app.vr.frame import FrameInput, FrameStats, Recording
from app.vr.transforms import head_pose, look_matrix
from sonicverse_core.errors import ConfigError, Interrupted, SonicverseError, check_stopped, stop_held

WARMUP_FRAMES = 2  # not counted in the frame statistics (their intervals include the first render and audio block)
SYNC_FRAMES = 90  # frames between syncs of the files a session writes as it runs (a second at 90 Hz)


@dataclass(frozen=True)
class SessionConfig:
    """scene: a scene spec; views: False = audio-only (no renderer is imported, tracking and audio go on);
    audio: 'offline' (rendered by the frame clock: headless), 'live' (app/audio_rt on a device) or 'none';
    robots: 0 or 1 robot sharing the scene; voice: what the user says in offline mode (text for espeak-ng);
    hrtf, reverb: the study conditions (HRTF or a time/level panner; reflections and reverb or none)."""

    scene: str = "builtin:apartment"
    views: bool = True
    audio: str = "offline"
    audio_device: str | None = None
    sample_rate: int = 48_000
    block: int = 256
    robots: int = 1
    robot_camera: bool = False
    msaa: bool = False
    cull_rooms: str = "auto"  # load only the rooms the eye may see: 'on', 'off', 'auto' (scenes of 250k+ triangles)
    seed: int = 0
    voice: str | None = "robot, come here please"
    write_frames: int = 0  # save every n-th stereo frame as a PNG (0: none)
    hrtf: bool = True  # False: an interaural time and level panner instead of the HRTF (every listener)
    reverb: bool = True  # False: no early reflections and no late reverb

    def __post_init__(self):
        if self.audio not in ("offline", "live", "none"):
            raise ConfigError(f"audio must be 'offline', 'live' or 'none', got '{self.audio}'")
        if self.robots not in (0, 1):
            raise ConfigError(f"a VR session has 0 or 1 robot, got {self.robots}")
        if self.write_frames < 0:
            raise ConfigError("write_frames must be >= 0")
        if self.cull_rooms not in ("auto", "on", "off"):
            raise ConfigError(f"cull_rooms must be 'auto', 'on' or 'off', got '{self.cull_rooms}'")


class VRSession:
    def __init__(self, cfg: SessionConfig, backend, task: FrameTask | None = None):
        from sonicverse_core.scene.spec import load_scene

        self.cfg, self.backend = cfg, backend
        self.task = task or FreeRoam(follow=cfg.robots > 0)
        self.scene = load_scene(cfg.scene)
        self.rng = np.random.default_rng(cfg.seed)
        self.events: list[str] = []
        self.world = None
        if cfg.robots:
            from sonicverse_core.world import World

            self.world = World(self.scene)
            self.grid = self.world.grid
        else:
            from sonicverse_core.geometry.navgrid import NavGrid

            self.grid = NavGrid(self.scene)
        self.spawn = self._spawn()
        if self.world is not None:  # the robot starts 1.5 m in front of the user where there is room
            self._place_robot()
        self.stats = FrameStats(backend.target_hz)
        self.recording = Recording({"scene": cfg.scene, "backend": backend.name, "target_hz": backend.target_hz,
                                    "seed": cfg.seed, "robots": cfg.robots})
        self.trajectory: list[np.ndarray] = []
        self.views = None
        self.frames_written: list[str] = []
        self._out: Path | None = None
        self._traj_log = None
        self.last_views = None
        self.robot_view = None
        self.audio = None
        backend.begin(self)
        if cfg.views:
            from app.scene.visual import VisualScene

            self.views = VisualScene(self.scene, backend.width, backend.height, msaa=cfg.msaa, robots=cfg.robots,
                                     cull_rooms={"on": True, "off": False}.get(cfg.cull_rooms, "auto"))
        self.audio = self._make_audio()
        self.task.reset(self)
        self.frame_index = 0
        self._last_in = None

    # --- set-up ---------------------------------------------------------------------------------------------------
    def _spawn(self) -> np.ndarray:
        living = next((r for r in self.scene.rooms if r.type == "living room"), None)
        room = living.name if living is not None else None
        return self.grid.sample(self.rng, 1, room=room)[0]

    def _place_robot(self) -> None:
        for d in (1.5, 1.0, 2.0, 0.7):
            for a in range(0, 360, 30):
                x = self.spawn[0] + d * np.cos(np.radians(a))
                y = self.spawn[1] + d * np.sin(np.radians(a))
                if self.world.free(x, y):
                    self.world.place_robot(x, y, (a + 180.0) % 360.0)
                    return

    def default_trajectory(self, rate: float):
        """What the user does in the headless backend: the task's simulated user when it has one, else a walk
        from the spawn point to a random point of another room."""
        from app.vr.headless import WalkTrajectory

        if hasattr(self.task, "headless_input"):
            return self.task.headless_input(self, rate)

        others = [r for r in self.scene.rooms if r.type != "living room"]
        goal = self.grid.sample(self.rng, 1, room=others[int(self.rng.integers(len(others)))].name)[0] \
            if others else self.grid.sample(self.rng, 1)[0]
        return WalkTrajectory(self.scene, self.grid, self.spawn, goal, rate)

    def _robots(self) -> list:
        if self.world is None:
            return []
        x, y, yaw = self.world.pose
        return [(float(x), float(y), float(self.world.ears[2]), float(yaw))]

    def _make_audio(self):
        cfg = self.cfg
        if cfg.audio == "none":
            return None
        from app.vr.audio import LiveAudio, OfflineAudio, scene_sources

        sources = self.task.audio_sources(self.scene) if hasattr(self.task, "audio_sources") else \
            scene_sources(self.scene)
        head = (self.spawn[0], self.spawn[1], self.scene.floor_z + 1.6, 0.0, 0.0)
        if cfg.audio == "live":
            return LiveAudio(self.scene, sources, self._robots(), head, device=cfg.audio_device,
                             sample_rate=cfg.sample_rate, block=cfg.block, hrtf=cfg.hrtf, reverb=cfg.reverb)
        voice = None
        if cfg.voice:
            from assets_manifest.speech import speak

            voice = speak(cfg.voice, sample_rate=cfg.sample_rate)[0]
        return OfflineAudio(self.scene, sources, self._robots(), head, cfg.sample_rate, cfg.block, voice=voice,
                            hrtf=cfg.hrtf, reverb=cfg.reverb)

    # --- the loop -------------------------------------------------------------------------------------------------
    def step(self, f: FrameInput) -> None:
        """One simulation step (deterministic in the frame inputs): the task, then the state is logged."""
        head_pose(f.head)  # validates (NaN pose -> PoseError)
        self.task.step(self, f)
        doors = [d.open_fraction for d in self.scene.doors]
        rb = list(self.world.pose) if self.world is not None else []
        row = np.array([f.t, *f.head[:3, 3], *rb, *doors], np.float64)
        with stop_held():  # the row into the trajectory and its log, or into neither (a SIGTERM between them)
            self.trajectory.append(row)
            if self._traj_log is not None:
                self._traj_log.append((row,))

    def frame(self) -> bool:
        """One frame; False when the backend asks to stop. Raises :class:`Interrupted` once the process was told to
        stop (SIGTERM), even if that raise was swallowed on its way out of an earlier frame."""
        check_stopped()
        f = self.backend.wait_frame()
        t_in = time.perf_counter()
        interval = None if self._last_in is None else t_in - self._last_in
        self._last_in = t_in
        if f.quit:
            return False
        try:
            self.step(f)
        except Interrupted:  # SIGTERM landing mid-step (its handler raises this): stop, never skip it as a bad frame
            raise
        except SonicverseError as exc:  # a bad input frame (NaN pose...) is reported and skipped: the session lives
            self.events.append(f"frame {f.index}: {exc}")
            return True
        self.recording.add(f)  # the frames that were simulated: a replay goes through the same steps
        robots = self._robots()
        if self.audio is not None:
            if self.audio.live:
                self.audio.update(f.t, f.head, robots, hands=f.hands)
            else:
                self.audio.update(f.t + f.dt, f.head, robots)
        views = None
        if self.views is not None:
            rb = [tuple(self.world.pose)] if self.world is not None else []
            self.views.sync(f.head, f.hands, f.hands_valid, rb)
            views = self.views.render_views(f.head, self.backend.eye_to_head, self.backend.projections)
            if self.cfg.robot_camera and self.world is not None:
                self.robot_view = self.views.render_camera(look_matrix(*self.world.camera))
            self.last_views = views
            if self.cfg.write_frames and self._out is not None and f.index % self.cfg.write_frames == 0:
                self._write_frame(f.index, views)
        self.backend.submit(views)
        if interval is not None and f.index >= WARMUP_FRAMES:  # frame 0 compiles shaders and casts first rays
            self.stats.add(interval, time.perf_counter() - t_in)
        self.frame_index += 1
        return not getattr(self.task, "done", False)  # a task that is over ends the run (its summary says how)

    def run(self, frames: int | None = None, out: str | Path | None = None) -> dict:
        """Run until the backend stops or ``frames`` frames; returns :meth:`summary`. With ``out``, the input
        recording (input.svrec), the trajectory (trajectory.svlog) and the audio at the ears (WAV) are written as
        the session runs and synced every second, stats.json every 5 s: a kill loses about a second."""
        if out is not None:
            self._open_sinks(Path(out))
        self._last_in = None
        n = 0
        while frames is None or n < frames:
            if not self.frame():
                break
            n += 1
            if self._out is not None and n % SYNC_FRAMES == 0:
                self._sync(stats=n % (5 * SYNC_FRAMES) == 0)
        return self.summary()

    def _open_sinks(self, out: Path) -> None:
        from sonicverse_core.storage import RecordLog

        out.mkdir(parents=True, exist_ok=True)
        self._out = out
        self.recording.stream_to(out / "input.svrec", sync_every=SYNC_FRAMES)
        width = len(self._traj_columns())
        self._traj_log = RecordLog(out / "trajectory.svlog", np.dtype([("row", "<f8", (width,))]),
                                   {"format": "sonicverse-trajectory", "columns": self._traj_columns()},
                                   sync_every=SYNC_FRAMES)
        for row in self.trajectory:
            self._traj_log.append((row,))
        if self.audio is not None:
            for ears, name in zip(self.audio.ears, ("binaural.wav", "robot_ears.wav")):
                ears.stream_to(out / name)

    def _traj_columns(self) -> list[str]:
        rb = ["robot_x", "robot_y", "robot_yaw"] if self.world is not None else []
        return ["t", "head_x", "head_y", "head_z", *rb, *(f"door:{d.name}" for d in self.scene.doors)]

    def _sync(self, stats: bool = False) -> None:
        """Push what the sinks hold to the disk (and stats.json, replaced atomically)."""
        from sonicverse_core.storage import write_text_atomic

        self.recording.sync()
        if self._traj_log is not None:
            self._traj_log.sync()
        if self.audio is not None:
            for ears in self.audio.ears:
                ears.flush()
        if stats and self._out is not None:
            write_text_atomic(self._out / "stats.json", json.dumps({**self.summary(), "partial": True}, indent=1))

    def _write_frame(self, k: int, views: np.ndarray) -> None:
        from PIL import Image

        d = self._out / "frames"
        d.mkdir(exist_ok=True)
        name = f"frames/stereo_{k:05d}.png"
        Image.fromarray(np.concatenate(list(views), axis=1)).save(self._out / name)
        self.frames_written.append(name)

    def summary(self) -> dict:
        s = self.stats.summary()
        s.update({"backend": self.backend.name, "scene": self.cfg.scene, "views": self.views is not None,
                  "eye_size": [self.backend.width, self.backend.height], "audio": self.cfg.audio,
                  "task": {"name": self.task.name, **self.task.summary()}, "events": list(self.events)})
        if self.audio is not None:
            s["audio_seconds"] = round(self.audio.heard(0).shape[1] / self.cfg.sample_rate, 3)
            if self.audio.live:
                s["audio_telemetry"] = self.audio.telemetry()
                s["events"] += self.audio.events
        return s

    def save(self, out) -> list[str]:
        """Finish the session's outputs in ``out``: stats.json, input.svrec and input.npz (replayable),
        trajectory.npy, binaural.wav (the user's ears), robot_ears.wav (what the robot heard), the last stereo
        frame. Files streamed while running are closed; the others are replaced atomically."""
        from sonicverse_core.storage import atomic_write, write_text_atomic

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        streamed = self._out is not None and out.resolve() == self._out.resolve()
        if not streamed:
            self.recording.save(out / "input.svrec")
        self.recording.close()
        if self._traj_log is not None:
            self._traj_log.close()
        written = ["stats.json", "input.svrec", "input.npz", "trajectory.npy"]
        self.recording.save(out / "input.npz")
        with atomic_write(out / "trajectory.npy") as fh:
            np.save(fh, np.array(self.trajectory))
        if self.audio is not None:
            for ears, name in zip(self.audio.ears, ("binaural.wav", "robot_ears.wav")):
                if not streamed:
                    ears.stream_to(out / name)
                ears.close()
                written.append(name)
        if self.last_views is not None:
            from PIL import Image

            with atomic_write(out / "last_stereo.png") as fh:
                Image.fromarray(np.concatenate(list(self.last_views), axis=1)).save(fh, format="PNG")
            written.append("last_stereo.png")
        written += self.frames_written
        summary = {**self.summary(), "config": asdict(self.cfg), "files": written}
        write_text_atomic(out / "stats.json", json.dumps(summary, indent=1))
        return written

    def close(self) -> None:
        if self.audio is not None:
            self.events += self.audio.close()
            self.audio = None
        self.backend.close()  # first: its textures live in the views' GL context
        if self.views is not None:
            self.views.close()
            self.views = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
