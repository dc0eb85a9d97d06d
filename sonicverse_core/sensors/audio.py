"""What a robot hears: binaural audio rendered continuously across steps by the acoustic engine, a rolling
window of it, its spectrogram, and the robot's own ego-noise (sim-to-real).

Spectrogram as in SoundSpaces / SAVi (``librosa.stft(x, n_fft=512, hop_length=160, win_length=400)``): a periodic
400-sample Hann window (librosa's ``get_window("hann", 400, fftbins=True)``, 25 ms at 16 kHz), hop 160 (10 ms),
512-point FFT, magnitude average-pooled (``pool`` bins x frames), then log1p. One difference, on purpose: librosa
centres frames on the hop grid and pads the signal's two ends (reflect in SoundSpaces' librosa); a stream has no
future samples, so our frames are whole windows of the last ``window`` seconds, the newest ending with the newest
sample (librosa with ``center=False`` on that window). Each frame's magnitude equals librosa's for the same
samples (tested against ``torch.stft``, which follows the same definition).
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.errors import ConfigError

N_FFT, HOP, WIN = 512, 160, 400


def hann_periodic(n: int) -> np.ndarray:
    """The periodic Hann window of length n (scipy/librosa ``fftbins=True``): 0.5 - 0.5 cos(2 pi k / n)."""
    return (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n)).astype(np.float32)


class Spectrogram:
    """Magnitude STFT of a (2, n) window -> (2, F, T) float32, pooled and log1p'd. Frames and window are
    precomputed: one batched rfft per call."""

    def __init__(self, n: int, pool: tuple[int, int] = (4, 2)):
        if n < WIN:
            raise ConfigError(f"the audio window must hold at least {WIN} samples, got {n}")
        pf, pt = int(pool[0]), int(pool[1])
        if pf < 1 or pt < 1:
            raise ConfigError(f"spectrogram pooling must be >= 1, got {pool}")
        self.n, self.pool = n, (pf, pt)
        self.frames = (n - WIN) // HOP + 1
        self.bins = (N_FFT // 2 // pf) * pf  # the Nyquist bin is dropped when pooling
        self.F, self.T = self.bins // pf, self.frames // pt
        # frames end-aligned: the last one ends with the newest sample
        self._idx = (n - WIN) % HOP + np.arange(WIN)[None, :] + HOP * np.arange(self.frames)[:, None]
        self._win = hann_periodic(WIN)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (2, self.F, self.T)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        frames = x[:, self._idx] * self._win  # (2, frames, WIN)
        mag = np.abs(np.fft.rfft(frames, N_FFT, axis=-1))[:, self.frames - self.T * self.pool[1]:, : self.bins]
        pf, pt = self.pool
        mag = mag.reshape(2, self.T, pt, self.F, pf).mean(axis=(2, 4))
        return np.log1p(mag.transpose(0, 2, 1)).astype(np.float32)


class StreamingSpectrogram:
    """The same spectrogram as :class:`Spectrogram` over the last ``n`` samples of a stream, computing only the
    STFT frames each new block completes (10 per 0.1 s step instead of 98). Equal to the full computation over the
    window when ``n`` and every block are multiples of the hop (checked in the tests)."""

    def __init__(self, n: int, pool: tuple[int, int] = (4, 2)):
        self.full = Spectrogram(n, pool)
        if n % HOP:
            raise ConfigError(f"a streaming spectrogram needs a window that is a multiple of {HOP} samples, got {n}")
        self.shape = self.full.shape
        self._mag = np.zeros((2, self.full.frames, N_FFT // 2 + 1), np.float32)
        self._tail = np.zeros((2, WIN - HOP), np.float32)  # samples before the next frame's hop
        self._win = self.full._win
        self._idx: dict[int, np.ndarray] = {}  # frame indices per block length

    def reset(self) -> None:
        self._mag[:] = 0.0
        self._tail[:] = 0.0

    def push(self, block: np.ndarray) -> np.ndarray:
        b = block.shape[1]
        if b % HOP:
            raise ConfigError(f"streaming spectrogram blocks must be multiples of {HOP} samples, got {b}")
        x = np.concatenate([self._tail, block.astype(np.float32, copy=False)], axis=1)
        k = b // HOP
        idx = self._idx.get(k)
        if idx is None:
            idx = self._idx[k] = np.arange(WIN)[None, :] + HOP * np.arange(k)[:, None]
        mag = np.abs(np.fft.rfft(x[:, idx] * self._win, N_FFT, axis=-1)).astype(np.float32)
        F = self._mag.shape[1]
        if k >= F:
            self._mag[:] = mag[:, -F:]
        else:
            self._mag[:, :-k] = self._mag[:, k:]
            self._mag[:, -k:] = mag
        self._tail = x[:, -(WIN - HOP):].copy()
        f = self.full
        pf, pt = f.pool
        m = self._mag[:, F - f.T * pt:, : f.bins].reshape(2, f.T, pt, f.F, pf).mean(axis=(2, 4))
        return np.log1p(m.transpose(0, 2, 1)).astype(np.float32)


def ego_noise(seconds: float, sample_rate: int, rng: np.random.Generator) -> np.ndarray:
    """A robot's own noise (mono float32, RMS 1): the drive motors' whine (harmonics of a jittering ~140 Hz) over
    low-passed rumble and a little broadband hiss, as a stand-in for a recorded TurtleBot ego-noise track."""
    from scipy import signal

    n = int(seconds * sample_rate)
    f0 = 140.0 * (1 + 0.03 * signal.sosfilt(signal.butter(1, 2.0, fs=sample_rate, output="sos"),
                                            rng.standard_normal(n)) * 20)
    ph = 2 * np.pi * np.cumsum(f0) / sample_rate
    whine = sum(rng.uniform(0.2, 1.0) / k * np.sin(k * ph + rng.uniform(0, 2 * np.pi)) for k in range(1, 7))
    rumble = signal.sosfilt(signal.butter(2, 300.0, fs=sample_rate, output="sos"), rng.standard_normal(n))
    hiss = 0.05 * rng.standard_normal(n)
    x = whine + 2.0 * rumble / max(np.std(rumble), 1e-12) + hiss
    x -= x.mean()
    return (x / max(np.sqrt(np.mean(x * x)), 1e-12)).astype(np.float32)


class BinauralWindow:
    """The last ``n`` binaural samples (2, n), updated block by block."""

    def __init__(self, n: int):
        self.buf = np.zeros((2, n), np.float32)

    def push(self, block: np.ndarray) -> None:
        b = block.shape[1]
        if b >= self.buf.shape[1]:
            self.buf[:] = block[:, -self.buf.shape[1]:]
        else:
            self.buf[:, :-b] = self.buf[:, b:]
            self.buf[:, -b:] = block

    def clear(self) -> None:
        self.buf[:] = 0.0
