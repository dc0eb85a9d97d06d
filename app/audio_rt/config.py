"""Settings of the real-time audio pipeline and the scene it renders (both picklable: they cross to the worker)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonicverse_core.errors import ConfigError

# a few shared-memory telemetry slots (int64)
CALLBACKS, XRUNS, IN_OVERFLOW, OUT_UNDERFLOW, ERRORS, STATE, FAULTS, FRAMES, POSE_FRAMES, POSE_TORN, PID, \
    ERROR_SEQ, PRIMING, ROBOT_BLOCKS, ROBOT_SKIPPED, MIC_NONFINITE, RECOVERIES, CB_POLICY, CB_PRIORITY, \
    CB_NICE, CB_TID, N_TELE = range(22)
# float64 slots
LAT_IN, LAT_OUT, LAST_CALLBACK, SAMPLE_RATE, N_TELEF = range(5)
STARTING, RUNNING, STOPPED, FAILED, LOST = range(5)  # the worker's STATE slot
DURATIONS = 1 << 16  # callback durations kept (about 5.8 min at 48 kHz / 256)
XRUN_LOG = 256  # callback index of the newest xruns (when they happened, for study logs and diagnosis)


@dataclass(frozen=True)
class AudioConfig:
    """The stream. device / input_device: a PortAudio device name (substring) or index, None for the default;
    mode: 'process' (the callback and the DSP in their own process: the main loop's GIL cannot delay them and a
    vanished device cannot take the application down) or 'thread' (in this process; for measurement)."""

    device: str | int | None = None
    input_device: str | int | None = None
    sample_rate: int = 48_000
    block: int = 256
    latency: str | float = "low"
    mode: str = "process"
    mic: bool = True
    mic_channel: int = 0
    mic_gain: float = 1.0
    sidetone: float = 0.0  # the user hearing their own voice in the scene: off by default
    ring_seconds: float = 4.0
    test_signal: bool = False  # loopback test: noise bursts mixed into the output
    start_timeout: float = 120.0

    def __post_init__(self):
        if self.mode not in ("process", "thread"):
            raise ConfigError(f"audio mode must be 'process' or 'thread', got '{self.mode}'")
        if not (8000 <= self.sample_rate <= 192_000):
            raise ConfigError(f"sample rate must be within 8-192 kHz, got {self.sample_rate}")
        if not (16 <= self.block <= 8192) or self.block & (self.block - 1):
            raise ConfigError(f"block size must be a power of two within 16-8192 frames, got {self.block}")
        if not (0 <= self.sidetone <= 4) or not (0 <= self.mic_gain <= 100) or self.mic_channel < 0:
            raise ConfigError("sidetone must be in [0, 4], mic_gain in [0, 100], mic_channel >= 0")
        if not (0.5 <= self.ring_seconds <= 600):
            raise ConfigError("ring_seconds must be within 0.5-600 s")


@dataclass
class SourceSpec:
    sound: str | np.ndarray  # a sound bank name ('sofa/2'), a file, or samples
    position: tuple = (0.0, 0.0, 1.0)
    gain: float = 1.0
    loop: bool = True
    sample_rate: int | None = None  # of the samples, when sound is an array


@dataclass
class AudioScene:
    """What the audio side renders: a scene spec (None: free field), its sources, robot listeners, the user's
    initial head pose (x, y, z, yaw, pitch) and the engine settings that are not the stream's."""

    spec: str | None = "builtin:apartment"
    sources: list[SourceSpec] = field(default_factory=list)
    robots: list[tuple] = field(default_factory=list)  # (x, y, z, yaw) each
    head: tuple = (0.0, 0.0, 1.6, 0.0, 0.0)
    occlusion: bool = True
    early_reflections: bool = True
    late_reverb: bool = True
    hrtf: bool = True  # False: an interaural time and level panner (RenderConfig output 'stereo')
    bake_rays: int = 2000
    occlusion_budget: int = 2  # source-listener segments recast per block at most (a door recasts what it affects)
    mic_directivity: float = 0.5  # speech is louder in front of the mouth
    warmup_blocks: int = 64
    doors: tuple = ()  # the scene's door names, in its order (filled in by the engine)
    door_open: tuple = ()  # and their open fractions at the start
