"""HRIR sets: the embedded MIT KEMAR (as shipped by the `slab` package) and any SOFA SimpleFreeFieldHRIR file.

Directions are unit vectors in the head frame of SOFA: x forward, y left, z up. The KEMAR set is converted once
from slab's data file (checked against the manifest's sha256) into an .npz under the cache dir.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sonicverse_core.errors import AssetError

KEMAR = "hrtf/mit_kemar_normal_pinna"


@dataclass(frozen=True)
class HrirSet:
    """sample_rate (Hz); directions : (n, 3) unit vectors, head frame (x fwd, y left, z up);
    hrirs : (n, 2, taps) float32, left ear first; name."""

    name: str
    sample_rate: int
    directions: np.ndarray
    hrirs: np.ndarray


def sph_to_vec(azimuth_deg, elevation_deg) -> np.ndarray:
    """SOFA spherical (azimuth counter-clockwise from front, elevation up) -> unit vectors (n, 3)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def _slab_file() -> Path:
    try:
        import importlib.util

        spec = importlib.util.find_spec("slab")
    except (ImportError, ValueError):
        spec = None
    if spec is None or spec.origin is None:
        raise AssetError("the embedded MIT KEMAR HRTF ships inside the 'slab' package: "
                         "install it with `.venv/bin/pip install slab==1.8.2` (make setup does)")
    f = Path(spec.origin).parent / "data" / "mit_kemar_normal_pinna.bz2"
    if not f.is_file():
        raise AssetError(f"MIT KEMAR data file missing from the slab package ({f}); reinstall slab==1.8.2")
    return f


def kemar() -> HrirSet:
    """The MIT KEMAR HRIRs (710 directions, 44.1 kHz, 512 taps)."""
    from assets_manifest import cache_dir, entry, sha256_file

    src = _slab_file()
    want = entry(KEMAR)["sha256"]
    cached = cache_dir() / f"kemar-v2-{want[:12]}.npz"
    if cached.is_file():
        try:
            with np.load(cached) as z:
                sr, dirs, hrirs = int(z["sample_rate"]), z["directions"], z["hrirs"]
            if not (hrirs.ndim == 3 and hrirs.shape[1] == 2 and dirs.shape == (len(hrirs), 3)
                    and np.isfinite(hrirs).all() and np.isfinite(dirs).all() and 8000 <= sr <= 192000):
                raise ValueError(f"shapes {hrirs.shape} / {dirs.shape}, or non-finite values")
            return HrirSet("mit_kemar", sr, dirs, hrirs)
        except Exception as exc:  # noqa: BLE001 - a corrupt or foreign cache file: rebuilt below
            import logging

            logging.getLogger(__name__).warning("HRTF cache %s is corrupt (%s): rebuilt", cached, exc)
            cached.unlink(missing_ok=True)
    got = sha256_file(src)
    if got != want:
        raise AssetError(f"MIT KEMAR data file {src} is corrupt or a different version (sha256 {got[:12]}..., "
                         f"expected {want[:12]}...); reinstall slab==1.8.2")
    import slab

    h = slab.HRTF(str(src)) if not hasattr(slab.HRTF, "kemar") else slab.HRTF.kemar()
    vp = np.asarray(h.sources.vertical_polar, dtype=np.float64)
    dirs = sph_to_vec(vp[:, 0], vp[:, 1])
    hrirs = np.stack([np.asarray(f.data, np.float64).T for f in h.data]).astype(np.float32)
    sr = int(h.samplerate)
    from sonicverse_core.storage import atomic_write

    with atomic_write(cached) as fh:
        np.savez(fh, sample_rate=sr, directions=dirs, hrirs=hrirs)
    return HrirSet("mit_kemar", sr, dirs, hrirs)


def load_sofa(path: str | Path) -> HrirSet:
    """A SOFA SimpleFreeFieldHRIR file (through sofar)."""
    p = Path(path)
    if not p.is_file():
        raise AssetError(f"SOFA file not found: {p}")
    try:
        import sofar
    except ImportError:
        raise AssetError("reading SOFA files needs 'sofar': .venv/bin/pip install sofar") from None
    try:
        s = sofar.read_sofa(str(p), verify=False, verbose=False)
    except Exception as exc:
        raise AssetError(f"cannot read SOFA file {p}: {exc}") from None
    conv = str(getattr(s, "GLOBAL_SOFAConventions", ""))
    if conv != "SimpleFreeFieldHRIR":
        raise AssetError(f"{p}: SOFA convention '{conv}' is not SimpleFreeFieldHRIR")
    ir = np.asarray(s.Data_IR, dtype=np.float64)
    if ir.ndim != 3 or ir.shape[1] != 2:
        raise AssetError(f"{p}: Data_IR must be (M, 2, N), got {ir.shape}")
    pos = np.asarray(s.SourcePosition, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[0] != ir.shape[0] or pos.shape[1] < 2 or not np.isfinite(pos).all():
        raise AssetError(f"{p}: SourcePosition must be (M, 3) finite values for M = {ir.shape[0]} measurements, "
                         f"got {pos.shape}")
    ptype = str(getattr(s, "SourcePosition_Type", "spherical")).lower()
    if ptype.startswith("cartesian"):
        radius = np.linalg.norm(pos, axis=1)
        if np.any(radius <= 0):
            raise AssetError(f"{p}: a source position at the head's centre has no direction")
        dirs = pos / radius[:, None]
    else:
        radius = pos[:, 2] if pos.shape[1] > 2 else np.ones(len(pos))
        dirs = sph_to_vec(pos[:, 0], pos[:, 1])
    # several radii (near-field sets): keep the farthest measurement of each direction (the far field)
    key = np.round(dirs, 5)
    order = np.lexsort((-radius, *key.T[::-1]))
    _, first = np.unique(key[order], axis=0, return_index=True)
    keep = np.sort(order[first])
    dirs, ir = dirs[keep], ir[keep]
    sr = int(np.asarray(s.Data_SamplingRate).ravel()[0])
    if not np.all(np.isfinite(ir)):
        raise AssetError(f"{p}: HRIRs contain NaN or infinite values")
    return HrirSet(p.stem, sr, dirs, ir.astype(np.float32))
