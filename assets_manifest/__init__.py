"""Every asset Sonicverse uses, listed in manifest.json (name, kind, licence, origin, sha256, size), and the code
that makes the built-in ones: the procedural sound bank, espeak-ng speech, and the embedded HRTF."""
from __future__ import annotations

import hashlib
import json
import os
from functools import lru_cache
from pathlib import Path

from sonicverse_core.errors import AssetError

MANIFEST = Path(__file__).with_name("manifest.json")


def cache_dir() -> Path:
    """Where derived assets are cached: $SONICVERSE_CACHE, else the platform's user cache folder (platformdirs:
    ~/.cache/sonicverse on Linux, ~/Library/Caches/sonicverse on macOS, %LOCALAPPDATA%\\sonicverse\\Cache on
    Windows)."""
    env = os.environ.get("SONICVERSE_CACHE")
    if env:
        d = Path(env)
    else:
        import platformdirs

        d = Path(platformdirs.user_cache_dir("sonicverse", appauthor=False))
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise AssetError(f"cannot create the cache folder {d} ({exc.strerror}): set SONICVERSE_CACHE to a writable "
                         f"folder") from None
    return d


@lru_cache(maxsize=1)
def manifest() -> dict:
    try:
        data = json.loads(MANIFEST.read_text())
    except (OSError, ValueError) as exc:
        raise AssetError(f"asset manifest {MANIFEST} is missing or corrupt ({exc}); restore it with git checkout") \
            from None
    return {a["name"]: a for a in data["assets"]}


def entry(name: str) -> dict:
    try:
        return manifest()[name]
    except KeyError:
        raise AssetError(f"unknown asset '{name}'; assets_manifest/manifest.json lists them") from None


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
