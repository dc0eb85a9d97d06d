"""The block renderer: N sources, one or more listeners, (2, block) float32 binaural output per listener.

Per block and listener: every source's signal is read from its history ring at a per-ear fractional delay
(propagation + the HRTF's onset delay; the delay ramps across the block, which gives Doppler without clicks); a
distance gain (Resonance Audio's log rolloff, min/max distance) with a bounded near-field boost ramps across the
block; air absorption and occlusion (per-band transmission of every surface the source-listener segment crosses,
smoothed across blocks) shape the spectrum together with the interpolated HRIR in one FFT multiply; a change of
direction crossfades between the old and new filter on the input side (exact, click-free). Late reverb is a shared
FDN per listener driven by the probes' RT60 (inverse-distance interpolated as the listener moves), with a send
that falls with source distance following Barron's revised theory (-0.174 r/T dB). A transparent peak limiter
acts only when a block would exceed 0.99. Memory is allocated at construction and when sources are added.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonicverse_core.acoustics.probes import AIR_ABSORPTION, SPEED_OF_SOUND
from sonicverse_core.errors import ConfigError, PoseError
from sonicverse_core.scene.materials import BANDS, material_arrays


@dataclass(frozen=True)
class RenderConfig:
    sample_rate: int = 48_000
    block: int = 256
    output: str = "binaural"  # binaural | stereo (pan) | mono
    hrtf: str = "kemar"  # or a .sofa path
    occlusion: bool = True
    late_reverb: bool = True
    rolloff: str = "log"  # log | linear | none
    min_distance: float = 1.0
    max_distance: float = 500.0
    near_field_gain: float = 3.0  # 0..9 (Resonance: at most +19 dB)
    occlusion_smoothing: float = 0.75

    def __post_init__(self):
        if not (8000 <= self.sample_rate <= 192000):
            raise ConfigError(f"sample rate must be within 8-192 kHz, got {self.sample_rate}")
        if not (16 <= self.block <= 8192):
            raise ConfigError(f"block size must be within 16-8192 frames, got {self.block}")
        if self.output not in ("binaural", "stereo", "mono"):
            raise ConfigError(f"output must be binaural, stereo or mono, got '{self.output}'")
        if self.rolloff not in ("log", "linear", "none"):
            raise ConfigError(f"rolloff must be log, linear or none, got '{self.rolloff}'")
        if not (0 < self.min_distance < self.max_distance):
            raise ConfigError("need 0 < min_distance < max_distance")


def distance_gain(d: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Rolloff gain (Resonance Audio's curves) times the near-field boost under 1 m."""
    d = np.asarray(d, float)
    d0, D = max(cfg.min_distance, 1.0) if cfg.rolloff == "log" else cfg.min_distance, cfg.max_distance
    if cfg.rolloff == "log":
        g = (1 / (np.maximum(d, d0) - d0 + 1) - 1 / (1 + D - d0)) / (1 - 1 / (1 + D - d0))
    elif cfg.rolloff == "linear":
        g = np.clip((D - np.maximum(d, d0)) / (D - d0), 0, 1)
    else:
        g = np.ones_like(d)
    g = np.where(d > D, 0.0, g)
    near = 1 + (1 / np.maximum(d, 0.1) - 1) * np.clip(cfg.near_field_gain, 0, 9) / 9 * (d < 1)
    return g * near


@dataclass
class Source:
    """A sound source. signal (n,) float32 at the engine rate; loop; position (3,); gain; or live=True to feed
    blocks with :meth:`push`. attached_to: a scene object's name whose pose moves the source."""

    signal: np.ndarray | None
    position: np.ndarray
    loop: bool = True
    gain: float = 1.0
    live: bool = False
    attached_to: str | None = None
    cursor: int = 0
    pending: np.ndarray | None = field(default=None, repr=False)

    def push(self, block: np.ndarray) -> None:
        self.pending = np.asarray(block, np.float32)


@dataclass
class Listener:
    position: np.ndarray
    yaw: float = 0.0  # degrees, 0 faces +x, 90 faces +y

    def head_frame(self, world: np.ndarray) -> np.ndarray:
        """World vectors (n, 3) -> head frame (x forward, y left, z up)."""
        c, s = np.cos(np.radians(self.yaw)), np.sin(np.radians(self.yaw))
        x, y = world[:, 0], world[:, 1]
        return np.stack([c * x + s * y, -s * x + c * y, world[:, 2]], 1)


class AcousticRenderer:
    def __init__(self, scene=None, config: RenderConfig = RenderConfig(), probes=None, hrtf=None):
        self.cfg = cfg = config
        self.scene = scene
        self.sources: list[Source] = []
        self.listeners: list[Listener] = []
        self.subsystems = ["direct", "distance", "air_absorption"]
        self.hrtf = None
        if cfg.output == "binaural":
            from assets_manifest.hrtf import kemar, load_sofa
            from sonicverse_core.acoustics.hrtf import HrtfInterpolator

            self.hrtf = hrtf or HrtfInterpolator(kemar() if cfg.hrtf == "kemar" else load_sofa(cfg.hrtf),
                                                 cfg.sample_rate, taps=min(256, max(64, cfg.sample_rate // 187)))
            self.subsystems.append("hrtf")
        self.taps = self.hrtf.taps if self.hrtf else 1
        self.nfft = 1 << int(np.ceil(np.log2(cfg.block + self.taps + 16)))
        self.freqs = np.fft.rfftfreq(self.nfft, 1 / cfg.sample_rate)
        self.caster = None
        has_geometry = scene is not None and len(scene.static_mesh()) > 0
        if cfg.occlusion and has_geometry:
            from sonicverse_core.geometry.raycast import SceneRayCaster

            self.caster = SceneRayCaster(scene)
            self.subsystems.append("occlusion")
        self.probes = probes if (cfg.late_reverb and probes) else None
        if self.probes:
            self.subsystems.append("late_reverb")
        self._alpha, _, self._trans = material_arrays()
        self.hist = 1 << int(np.ceil(np.log2(int(cfg.max_distance / SPEED_OF_SOUND * cfg.sample_rate)
                                             + 2 * cfg.block + 64)))
        self._state: list[dict] = []
        self._ring = np.zeros((0, self.hist), np.float32)
        self.write = 0

    # --- setup ------------------------------------------------------------------------------------------------
    def add_source(self, signal=None, position=(0, 0, 0), loop=True, gain=1.0, live=False, attached_to=None,
                   sample_rate=None) -> Source:
        pos = np.asarray(position, float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise PoseError(f"source position must be 3 finite numbers, got {position}")
        if signal is not None:
            signal = np.asarray(signal, np.float32).ravel()
            if sample_rate is not None and sample_rate != self.cfg.sample_rate:
                from scipy.signal import resample_poly

                g = np.gcd(int(sample_rate), self.cfg.sample_rate)
                signal = resample_poly(signal, self.cfg.sample_rate // g, int(sample_rate) // g).astype(np.float32)
            if not np.all(np.isfinite(signal)):
                raise ConfigError("source signal contains NaN or infinite samples")
        elif not live:
            raise ConfigError("a source needs a signal or live=True")
        s = Source(signal, pos, loop, float(gain), live, attached_to)
        self.sources.append(s)
        self._ring = np.vstack([self._ring, np.zeros((1, self.hist), np.float32)])
        return s

    def add_listener(self, position=(0, 0, 1.5), yaw=0.0) -> Listener:
        lis = Listener(np.asarray(position, float), float(yaw))
        self.set_listener(lis, position, yaw)
        self.listeners.append(lis)
        st = {"prev": None, "tail": np.zeros((2, self.nfft)), "limit": 1.0}
        if self.probes:
            from sonicverse_core.acoustics.reverb import FDNReverb

            st["fdn"] = FDNReverb(self.cfg.sample_rate, self.cfg.block)
        self._state.append(st)
        return lis

    @staticmethod
    def set_listener(lis: Listener, position, yaw) -> None:
        p = np.asarray(position, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)) or not np.isfinite(yaw):
            raise PoseError(f"listener pose must be finite, got {position}, yaw {yaw}")
        lis.position, lis.yaw = p, float(yaw)

    # --- per block ---------------------------------------------------------------------------------------------
    def _advance_sources(self) -> None:
        B = self.cfg.block
        w = (self.write + np.arange(B)) % self.hist
        for i, s in enumerate(self.sources):
            if s.attached_to and self.scene is not None:
                s.position = self.scene.object(s.attached_to).position + np.array([0, 0, 0.3])
            if s.live:
                blk = s.pending if s.pending is not None and len(s.pending) == B else np.zeros(B, np.float32)
                s.pending = None
            else:
                n = len(s.signal)
                if s.loop:
                    blk = s.signal[(s.cursor + np.arange(B)) % n]
                else:
                    idx = s.cursor + np.arange(B)
                    blk = np.where(idx < n, s.signal[np.minimum(idx, n - 1)], 0.0)
                s.cursor += B
            self._ring[i, w] = blk * s.gain
        self.write = (self.write + B) % self.hist

    def _band_curve(self, band_amp: np.ndarray) -> np.ndarray:
        """(m, 9) amplitude per band -> (m, nfreq) smooth curve over FFT bins (log-frequency interpolation)."""
        lf = np.log2(np.maximum(self.freqs, BANDS[0]))
        return np.stack([np.interp(lf, np.log2(BANDS), a) for a in band_amp]) if len(band_amp) else \
            np.zeros((0, len(self.freqs)))

    def _occlusion(self, lis: Listener) -> np.ndarray:
        n = len(self.sources)
        amp = np.ones((n, len(BANDS)))
        if self.caster is None or n == 0:
            return amp
        a = np.array([s.position for s in self.sources])
        b = np.tile(lis.position, (n, 1))
        cr = self.caster.crossings(a, b)
        if len(cr.ray):
            key = np.unique(np.stack([cr.ray, cr.part], 1), axis=0)  # a part counts once per segment
            mats = {}
            for (r, p), m in zip(np.stack([cr.ray, cr.part], 1), cr.material):
                mats[(int(r), int(p))] = int(m)
            for r, p in key:
                amp[r] *= np.sqrt(self._trans[mats[(int(r), int(p))]])
        return amp

    def render_block(self) -> list[np.ndarray]:
        """Advance one block; returns one (2, block) float32 array per listener."""
        cfg, B = self.cfg, self.cfg.block
        if not self.listeners:
            raise ConfigError("add a listener before rendering")
        self._advance_sources()
        outs = []
        n = len(self.sources)
        for li, lis in enumerate(self.listeners):
            st = self._state[li]
            out = np.zeros((2, B))
            if n:
                pos = np.array([s.position for s in self.sources])
                rel = pos - lis.position
                dist = np.linalg.norm(rel, axis=1)
                head = lis.head_frame(rel)
                if self.hrtf is not None:
                    filt, onset = self.hrtf.lookup(np.where(dist[:, None] > 1e-6, head, [1.0, 0, 0]))
                else:
                    az = np.arctan2(head[:, 1], head[:, 0])
                    pan = np.stack([np.sqrt(0.5 * (1 + np.sin(az))), np.sqrt(0.5 * (1 - np.sin(az)))], 1)
                    if cfg.output == "mono":
                        pan = np.full((n, 2), np.sqrt(0.5))
                    filt = np.zeros((n, 2, 1))
                    filt[:, :, 0] = pan
                    onset = np.zeros((n, 2))
                gain = distance_gain(dist, cfg)
                occ = self._occlusion(lis)
                air = np.exp(-0.5 * AIR_ABSORPTION[None] * np.minimum(dist, cfg.max_distance)[:, None])
                prev = st.get("prev")
                if prev is None or len(prev["gain"]) != n:  # new sources start from their current state
                    prev = {"occ": occ, "gain": gain, "delay": None, "spec": None}
                if self.caster is not None:
                    occ = cfg.occlusion_smoothing * prev["occ"] + (1 - cfg.occlusion_smoothing) * occ
                spec = np.fft.rfft(filt, self.nfft, axis=-1) * self._band_curve(air * occ)[:, None, :]
                delay = np.minimum(dist, cfg.max_distance)[:, None] / SPEED_OF_SOUND + onset  # (n, 2) s
                p_delay = delay if prev["delay"] is None else prev["delay"]
                p_spec = spec if prev["spec"] is None else prev["spec"]
                ramp = (np.arange(B) + 1) / B
                d_smp = (p_delay[..., None] + (delay - p_delay)[..., None] * ramp) * cfg.sample_rate  # (n, 2, B)
                readpos = (self.write - B + np.arange(B)) - d_smp
                i0 = np.floor(readpos).astype(np.int64)
                fr = (readpos - i0).astype(np.float32)
                rows = np.arange(n)[:, None, None]
                x = self._ring[rows, i0 % self.hist] * (1 - fr) + self._ring[rows, (i0 + 1) % self.hist] * fr
                x = x * (prev["gain"][:, None, None] + (gain - prev["gain"])[:, None, None] * ramp)
                X_new = np.fft.rfft(x * ramp, self.nfft, axis=-1)
                X_old = np.fft.rfft(x * (1 - ramp), self.nfft, axis=-1)
                acc = np.einsum("nef,nef->ef", X_new, spec) + np.einsum("nef,nef->ef", X_old, p_spec)
                st["prev"] = {"occ": occ, "gain": gain, "delay": delay, "spec": spec}
                y = np.fft.irfft(acc, self.nfft, axis=-1)
                y[:, : self.nfft] += st["tail"]
                out += y[:, :B]
                st["tail"] = np.concatenate([y[:, B:], np.zeros((2, B))], axis=1)
                if "fdn" in st:
                    out += self._late(st, lis, dist, gain)
            outs.append(self._limit(st, out))
        return outs

    def _late(self, st, lis, dist, gain) -> np.ndarray:
        probes = self.probes
        P = np.array([p.position for p in probes])
        w = 1 / np.maximum(np.linalg.norm(P - lis.position, axis=1), 0.1) ** 2
        w /= w.sum()
        rt = np.einsum("k,kb->b", w, np.array([p.rt60 for p in probes]))
        vol = float(np.dot(w, [p.volume for p in probes]))
        lo, hi = float(np.mean(rt[2:5])), float(np.mean(rt[7:9]))
        st["fdn"].set_rt60(lo, hi)
        # diffuse-field level relative to the direct sound at 1 m: 16 pi / A, A = 0.161 V / T (Sabine)
        level = np.sqrt(16 * np.pi * max(lo, 0.05) / (0.161 * max(vol, 1.0)))
        barron = 10 ** (-0.174 * dist / max(lo, 0.05) / 20)  # Barron & Lee 1988: late level falls with distance
        B = self.cfg.block
        send = barron @ self._ring[:, (self.write - B + np.arange(B)) % self.hist]
        return st["fdn"].process(send) * level * 0.5

    @staticmethod
    def _limit(st, out: np.ndarray) -> np.ndarray:
        out = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
        peak = float(np.max(np.abs(out))) if out.size else 0.0
        target = min(1.0, 0.99 / peak) if peak > 0.99 else 1.0
        g = st["limit"]
        ramp = g + (target - g) * np.minimum(1.0, (np.arange(out.shape[1]) + 1) / max(1, out.shape[1] // 4))
        st["limit"] = target if target < 1.0 else min(1.0, g + 0.05)
        res = np.clip(out * ramp, -1.0, 1.0)
        res[np.abs(res) < 1e-30] = 0.0
        return res.astype(np.float32)

    def render(self, seconds: float) -> list[np.ndarray]:
        """Render ``seconds`` of audio: one (2, n) float32 array per listener."""
        blocks = int(np.ceil(seconds * self.cfg.sample_rate / self.cfg.block))
        outs = [[] for _ in self.listeners]
        for _ in range(blocks):
            for k, o in enumerate(self.render_block()):
                outs[k].append(o)
        return [np.concatenate(o, axis=1) for o in outs]
