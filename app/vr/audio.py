"""Audio for the VR loop: the user's ears and the robots' ears, with the user's voice at the avatar's mouth.

- :class:`LiveAudio`: the real-time pipeline of ``app/audio_rt`` (a sound card or JACK; the microphone is the
  voice). The loop hands it one pose frame per frame and never waits for it; what the user and robots heard is read
  back from its rings.
- :class:`OfflineAudio`: for headless sessions without an audio device. The same renderer, driven by the frame
  clock instead of a sound card: after each frame it renders the blocks up to the frame's time, with poses
  interpolated across them as the real-time side does. The voice is a recorded or synthesised signal.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
from assets_manifest import soundbank
from app.audio_rt.poses import PoseInterpolator, PoseLayout, mouth
from app.vr.transforms import head_pose
from sonicverse_core.errors import ConfigError, stop_held

# which objects sound in the VR app, first choice first: the sound bank's categories, those that sound on their own
# (a TV, running water) before the rest
_FIRST = ("standing_tv", "sink", "toilet", "shower", "bathtub")
SOUNDING = _FIRST + tuple(c for c in soundbank.CATEGORIES if c not in _FIRST)


def scene_sources(scene, n: int = 2) -> list[tuple[str, SourceSpec]]:
    """(object name, source) for up to ``n`` sounding objects of the scene (a TV, a sink...), looping."""
    out = []
    for cat in SOUNDING:
        obj = next((o for o in scene.objects if o.category == cat), None)
        if obj is not None and len(out) < n:
            out.append((obj.name, SourceSpec(sound=f"{cat}/0", position=tuple(obj.sound_position()),
                                              gain=0.5)))
    return out


class EarLog:
    """What one listener heard, kept in memory up to ``keep_s`` seconds (the oldest blocks are dropped: an hour of
    stereo float32 at 48 kHz would be 1.4 GB)."""

    def __init__(self, sample_rate: int, keep_s: float = 600.0):
        self.blocks: deque[np.ndarray] = deque()
        self.sr = sample_rate
        self.n, self.cap = 0, int(keep_s * sample_rate)
        self.sink = None  # a soundfile.SoundFile that gets every block as it comes (the whole session on disk)

    def stream_to(self, path) -> None:
        """Write every block from now on (and what is held already) to the WAV file ``path``."""
        import soundfile as sf

        self.close()
        self.sink = sf.SoundFile(str(path), "w", self.sr, 2, subtype="FLOAT")
        for b in self.blocks:
            self.sink.write(b.T)

    def flush(self) -> None:
        if self.sink is not None:
            self.sink.flush()  # libsndfile rewrites the header: a kill after this keeps every flushed sample

    def close(self) -> None:
        if self.sink is not None:
            self.sink.close()
            self.sink = None

    def add(self, block: np.ndarray) -> None:
        if block.shape[-1] == 0:
            return
        block = np.asarray(block, np.float32)
        with stop_held():  # on disk and in memory, or neither (a SIGTERM between them)
            if self.sink is not None:
                self.sink.write(block.T)
            self.blocks.append(block)
            self.n += block.shape[-1]
        while self.n - self.blocks[0].shape[-1] >= self.cap:
            self.n -= self.blocks.popleft().shape[-1]

    def heard(self) -> np.ndarray:
        return np.concatenate(self.blocks, axis=1) if self.blocks else np.zeros((2, 0), np.float32)

    def last(self, n: int) -> np.ndarray:
        """The last ``n`` samples (2, n), zeros where nothing was heard yet; reads only the blocks it needs."""
        out = np.zeros((2, n), np.float32)
        k = n
        for b in reversed(self.blocks):
            if k <= 0:
                break
            m = min(k, b.shape[1])
            out[:, k - m:k] = b[:, b.shape[1] - m:]
            k -= m
        return out


def source_positions(scene, sources) -> list:
    """Where each (name, spec) source is: the named object's sound position, or for a source no object carries
    (name None: a task's stimulus) its spec's position (tasks move it with :meth:`_Ears.move_source`)."""
    return [tuple(spec.position) if name is None else tuple(scene.object(name).sound_position())
            for name, spec in sources]


class _Ears:
    ears: list
    sources: list

    def heard(self, listener: int = 0) -> np.ndarray:
        """(2, n) float32: what listener 0 (the user) or a robot (1..) heard so far (the last 10 minutes at most)."""
        return self.ears[listener].heard()

    def last(self, listener: int, n: int) -> np.ndarray:
        """(2, n) float32: the last ``n`` samples listener ``listener`` heard (zeros before the start)."""
        return self.ears[listener].last(n)

    def move_source(self, i: int, position) -> None:
        """Move source ``i`` that no object carries (a task's stimulus) to ``position`` (x, y, z)."""
        from dataclasses import replace

        name, spec = self.sources[i]
        if name is not None:
            raise ConfigError(f"source {i} sounds at object '{name}': move the object")
        self.sources[i] = (None, replace(spec, position=tuple(float(v) for v in position)))


class OfflineAudio(_Ears):
    """Renders the user's and robots' ears block by block, following the frame clock."""

    live = False

    def __init__(self, scene, sources, robots: list, head: tuple, sample_rate: int = 48_000, block: int = 256,
                 voice: np.ndarray | None = None, hrtf: bool = True, reverb: bool = True):
        from app.audio_rt.core import build_renderer

        self.scene, self.sources = scene, sources
        setup = AudioScene(spec=scene.spec, sources=[s for _, s in sources], robots=list(robots), head=tuple(head),
                           hrtf=hrtf, early_reflections=reverb, late_reverb=reverb)
        cfg = AudioConfig(sample_rate=sample_rate, block=block, mic=voice is not None)
        self.r, _, self.mic, self.user, _ = build_renderer(setup, cfg, scene=scene)
        self.sr, self.block = sample_rate, block
        self.voice = None if voice is None else np.asarray(voice, np.float32)  # at sample_rate
        self.voice_at = 0
        self.samples = 0  # rendered so far
        self.layout = PoseLayout(n_robots=len(robots))
        self.interp = PoseInterpolator(self.layout)  # the real-time pipeline's, teleport rule included
        self.ears = [EarLog(sample_rate) for _ in self.r.listeners]

    def update(self, t: float, head: np.ndarray, robots: list, speaking: bool = True) -> None:
        """Render up to time ``t`` (s); head (4x4) and robots (x, y, z, yaw) are the poses at ``t``."""
        L = self.layout
        end = int(round(t * self.sr))
        for s, p in zip(self.r.sources, source_positions(self.scene, self.sources)):
            s.position = p
        n_blocks = max(0, -(-(end - self.samples) // self.block))
        block_s = self.block / self.sr
        self.interp.new_frame(L.frame(t, head_pose(head), robots=np.array(robots, float).reshape(-1, 4)),
                              interval=max(n_blocks, 1) * block_s)
        for _ in range(n_blocks):
            v = self.interp.advance(block_s)
            h = v[L.HEAD]
            self.r.set_listener(self.user, h[:3], h[3], h[4])
            for k, lis in enumerate(self.r.listeners[1:]):
                rb = v[L.ROBOTS.start + 4 * k: L.ROBOTS.start + 4 * k + 4]
                self.r.set_listener(lis, rb[:3], rb[3])
            if self.mic is not None:
                m, fwd = mouth(h)
                self.mic.position, self.mic.forward = m, fwd
                blk = np.zeros(self.block, np.float32)
                if speaking and self.voice is not None:
                    part = self.voice[self.voice_at:self.voice_at + self.block]
                    blk[:len(part)] = part
                    self.voice_at = (self.voice_at + self.block) % max(len(self.voice), 1)
                self.mic.push(blk)
            for log, out in zip(self.ears, self.r.render_block()):
                log.add(out)
            self.samples += self.block

    def close(self) -> list[str]:
        return []


class LiveAudio(_Ears):
    """The real-time pipeline (app/audio_rt) fed by the frame loop."""

    live = True

    def __init__(self, scene, sources, robots: list, head: tuple, device=None, sample_rate: int = 48_000,
                 block: int = 256, mic: bool = True, mode: str = "process", hrtf: bool = True, reverb: bool = True):
        from app.audio_rt.engine import AudioEngine

        self.scene, self.sources = scene, sources
        self.engine = AudioEngine(
            AudioConfig(device=device, sample_rate=sample_rate, block=block, mic=mic, mode=mode),
            AudioScene(spec=scene.spec, sources=[s for _, s in sources], robots=list(robots), head=tuple(head),
                       hrtf=hrtf, early_reflections=reverb, late_reverb=reverb))
        self.info = self.engine.start()
        self.doors = list(self.engine.scene.doors)
        self.sr = sample_rate
        self.ears = [EarLog(sample_rate) for _ in range(self.engine.n_listeners)]
        self.events: list[str] = []

    def update(self, t: float, head: np.ndarray, robots: list, hands=None, speaking: bool = True) -> None:
        fr = [self.scene.object(d).open_fraction for d in self.doors]
        hp = None if hands is None else np.asarray(hands)[:, :3, 3].ravel()
        self.engine.set_poses(head_pose(head), robots=robots, hands=hp,
                              sources=source_positions(self.scene, self.sources), doors=fr)
        for k, log in enumerate(self.ears):
            log.add(self.engine.read_ears(k))
        self.events += self.engine.poll()

    def telemetry(self) -> dict:
        return self.engine.telemetry()

    def close(self) -> list[str]:
        self.engine.stop()
        return self.events
