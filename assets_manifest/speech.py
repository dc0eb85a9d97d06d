"""Speech for voice tasks, made with espeak-ng (Debian package) and cached as WAV under the cache dir."""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess

import numpy as np

from sonicverse_core.errors import AssetError

log = logging.getLogger(__name__)


def espeak_path() -> str:
    exe = shutil.which("espeak-ng")
    if exe is None:
        raise AssetError("speech needs espeak-ng: install it with `apt-get install espeak-ng` (make setup does)")
    return exe


def speak(text: str, voice: str = "en-us", speed: int = 150, pitch: int = 50, pad_s: float = 0.4,
          sample_rate: int = 48_000) -> tuple[np.ndarray, int]:
    """Mono float32 speech of ``text`` at ``sample_rate``, padded with ``pad_s`` of silence on both sides."""
    import soundfile as sf
    from scipy.signal import resample_poly

    from assets_manifest import cache_dir

    if not text.strip():
        raise AssetError("cannot speak an empty text")
    key = hashlib.sha256(f"{text}|{voice}|{speed}|{pitch}".encode()).hexdigest()[:16]
    path = cache_dir() / "speech" / f"{key}.wav"
    x = None
    if path.is_file():  # a cached file is used only when it reads back whole and finite; otherwise made again
        try:
            x, sr = sf.read(str(path), dtype="float32", always_2d=True)
            if x.size == 0 or not np.isfinite(x).all():
                raise ValueError("empty or non-finite samples")
        except Exception as exc:  # noqa: BLE001 - libsndfile's errors come in several types
            log.warning("cached speech %s is corrupt (%s): made again", path, exc)
            x = None
    if x is None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.wav")
        r = subprocess.run([espeak_path(), "-v", voice, "-s", str(speed), "-p", str(pitch), "-w", str(tmp), text],
                           capture_output=True, text=True)
        if r.returncode != 0 or not tmp.is_file():
            raise AssetError(f"espeak-ng failed for voice '{voice}': {r.stderr.strip() or r.returncode}")
        x, sr = sf.read(str(tmp), dtype="float32", always_2d=True)
        if x.size == 0 or not np.isfinite(x).all():
            tmp.unlink(missing_ok=True)
            raise AssetError(f"espeak-ng made no usable audio for voice '{voice}' and text {text[:40]!r}")
        tmp.replace(path)
    x = x[:, 0]
    if sr != sample_rate:
        g = np.gcd(sr, sample_rate)
        x = resample_poly(x, sample_rate // g, sr // g).astype(np.float32)
    pad = np.zeros(int(pad_s * sample_rate), np.float32)
    return np.concatenate([pad, x, pad]), sample_rate


def espeak_version() -> str:
    r = subprocess.run([espeak_path(), "--version"], capture_output=True, text=True)
    return r.stdout.strip()


