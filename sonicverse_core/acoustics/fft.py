"""Real FFTs on fixed buffers for the per-block path (FFTW through pyFFTW).

NumPy's and SciPy's FFTs return a new array on every call; the renderer's overlap-save filters run several per block,
so the audio callback would allocate every block. A :class:`Plan` binds an FFTW plan to one input and one output
array once (when sources or listeners are added); :meth:`Plan.run` then transforms in place of those buffers and
allocates nothing. FFTW's ``FFTW_ESTIMATE`` planning is deterministic and takes microseconds; the inverse is
unnormalised (callers fold the 1/n into their gains) and may overwrite its input (the callers rebuild it every
block).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

_FLAGS = ("FFTW_ESTIMATE",)


@lru_cache(maxsize=None)
def band_bins(nfft: int, sample_rate: int) -> np.ndarray:
    """(9, nfft // 2 + 1): each octave band's weight over the bins of an nfft-point real FFT, linear in log
    frequency between band centres and flat beyond the end bands, so that ``amplitudes (..., 9) @ band_bins`` is a
    smooth per-band curve over the bins. Read-only and shared (cached per size and rate): copy it to write to it."""
    from sonicverse_core.scene.materials import BANDS

    lf = np.log2(np.maximum(np.fft.rfftfreq(nfft, 1 / sample_rate), BANDS[0]))
    bins = np.stack([np.interp(lf, np.log2(BANDS), e) for e in np.eye(len(BANDS))])
    bins.flags.writeable = False
    return bins


class Plan:
    """A real FFT (``inverse=False``: x real (..., n) -> X complex (..., n // 2 + 1)) or its unnormalised inverse
    along the last axis, bound to ``src`` and ``dst``; ``run()`` executes it."""

    def __init__(self, src: np.ndarray, dst: np.ndarray, inverse: bool = False):
        import pyfftw

        self.src, self.dst = src, dst
        self.n = dst.shape[-1] if inverse else src.shape[-1]
        if inverse:
            self._p = pyfftw.FFTW(src, dst, axes=(-1,), direction="FFTW_BACKWARD",
                                  flags=_FLAGS + ("FFTW_DESTROY_INPUT",), threads=1)
        else:
            self._p = pyfftw.FFTW(src, dst, axes=(-1,), flags=_FLAGS, threads=1)
        self.run = self._p.execute  # a bound method kept once: calling it creates no object

    def __repr__(self) -> str:
        return f"Plan({self.src.shape} -> {self.dst.shape})"


def rfft_plan(x: np.ndarray) -> tuple[Plan, np.ndarray]:
    """A forward plan for ``x`` (..., n) float32 into a new complex64 (..., n // 2 + 1) buffer; (plan, buffer)."""
    X = np.zeros(x.shape[:-1] + (x.shape[-1] // 2 + 1,), np.complex64)
    return Plan(x, X), X


def irfft_plan(X: np.ndarray, n: int) -> tuple[Plan, np.ndarray]:
    """An inverse plan for ``X`` (..., n // 2 + 1) complex64 into a new float32 (..., n) buffer (unnormalised: n
    times numpy's irfft); (plan, buffer)."""
    x = np.zeros(X.shape[:-1] + (n,), np.float32)
    return Plan(X, x, inverse=True), x
