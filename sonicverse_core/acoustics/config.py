"""The renderer's settings (:class:`RenderConfig`), checked when made: a bad value is a ConfigError, never a
renderer that misbehaves later."""
from __future__ import annotations

from dataclasses import dataclass

from sonicverse_core.errors import ConfigError


@dataclass(frozen=True)
class RenderConfig:
    sample_rate: int = 48_000
    block: int = 256
    output: str = "binaural"  # binaural (HRTF) | stereo (interaural time and level panner, no HRTF) | mono
    hrtf: str = "kemar"  # or a .sofa path
    hrtf_interpolation: str = "barycentric"  # or nearest
    hrtf_taps: int = 0  # 0: 4 ms worth at the engine rate
    occlusion: bool = True
    early_reflections: bool = True
    er_order: int = 1  # image-source order (1: 6 images per source, 2: 24)
    er_images: str = "room"  # room: images of the listener's room's own walls | box: of its probe's proxy box
    late_reverb: bool = True
    reverb: str = "convolution"  # convolution (synthesised binaural tails, exact per band) | fdn (cheaper)
    rolloff: str = "log"  # log | linear | none
    min_distance: float = 1.0
    max_distance: float = 500.0
    near_field_gain: float = 3.0  # 0..9 (Resonance: at most +19 dB)
    occlusion_smoothing: float = 0.75
    occlusion_tolerance: float = 0.02  # m a segment end moves before its rays are cast again
    occlusion_rays_per_block: int = 16  # segments recast per block at most (all of them when the scene changes)
    paths: bool = True  # sounds without line of sight also arrive around corners and through doorways
    diffraction: str = "fresnel"  # bend loss of a path: fresnel (per band, from each bend's detour) | none
    path_cell: float = 0.1  # m: the grid of the ear-height slice the paths are found on
    tail_seed: int = 0  # the convolution tails' noise: another seed, another realisation of the same decays
    tail_edt: bool = True  # the convolution tails fall at first at the probes' baked EDT, then at their RT60
    tail_buildup: float = 0.02  # s: the late part of a source in another room builds up as 1 - e^(-t / this); 0: off
    # the share of that late part that builds up at tail_buildup (a doorway's beam and its first reflections); the
    # rest builds up at the coupled rooms' own rate (coupling.late_split's buildup_tau; rooms of their own only).
    # 1: all at tail_buildup (before session 61)
    tail_beam: float = 0.7
    neighbour_tails: int = 1  # coupled rooms: the most rooms besides the slowest mode's heard apart (0..4)
    # auto: a convolution tail of 64 blocks or more is convolved in long partitions after its first few (the same
    # convolution, its work spread over the blocks: long_tail.py); uniform: every partition one block long
    tail_partitions: str = "auto"

    def __post_init__(self):
        if not (8000 <= self.sample_rate <= 192000):
            raise ConfigError(f"sample rate must be within 8-192 kHz, got {self.sample_rate}")
        if not (16 <= self.block <= 8192):
            raise ConfigError(f"block size must be within 16-8192 frames, got {self.block}")
        if self.output not in ("binaural", "stereo", "mono"):
            raise ConfigError(f"output must be binaural, stereo or mono, got '{self.output}'")
        if self.rolloff not in ("log", "linear", "none"):
            raise ConfigError(f"rolloff must be log, linear or none, got '{self.rolloff}'")
        if not (0 < self.min_distance < self.max_distance <= 5000):
            raise ConfigError("need 0 < min_distance < max_distance <= 5000 m")
        if self.hrtf_interpolation not in ("barycentric", "nearest"):
            raise ConfigError("hrtf_interpolation must be barycentric or nearest")
        if self.er_order not in (1, 2):
            raise ConfigError("er_order must be 1 or 2")
        if self.er_images not in ("room", "box"):
            raise ConfigError("er_images must be room or box")
        if self.reverb not in ("fdn", "convolution"):
            raise ConfigError("reverb must be fdn or convolution")
        if not (0 <= self.occlusion_smoothing < 1) or not (0 <= self.near_field_gain <= 9):
            raise ConfigError("occlusion_smoothing must be in [0, 1) and near_field_gain in [0, 9]")
        if not (0 <= self.occlusion_tolerance <= 10) or not (1 <= self.occlusion_rays_per_block <= 1_000_000):
            raise ConfigError("occlusion_tolerance must be in [0, 10] m and occlusion_rays_per_block >= 1")
        if self.diffraction not in ("fresnel", "none") or not (0.02 <= self.path_cell <= 1.0):
            raise ConfigError("diffraction must be fresnel or none and path_cell within 0.02..1 m")
        if not (0 <= self.tail_seed < 100_000):
            raise ConfigError(f"tail_seed must be within 0..99999, got {self.tail_seed}")
        if not (0.0 <= self.tail_buildup <= 0.2):
            raise ConfigError(f"tail_buildup must be within 0..0.2 s, got {self.tail_buildup}")
        if not (0.0 <= self.tail_beam <= 1.0):
            raise ConfigError(f"tail_beam must be within 0..1, got {self.tail_beam}")
        if not (0 <= self.neighbour_tails <= 4):
            raise ConfigError(f"neighbour_tails must be within 0..4, got {self.neighbour_tails}")
        if self.tail_partitions not in ("auto", "uniform"):
            raise ConfigError(f"tail_partitions must be auto or uniform, got '{self.tail_partitions}'")
        if self.hrtf_taps and not (16 <= self.hrtf_taps <= 4096):
            raise ConfigError("hrtf_taps must be within 16..4096")
