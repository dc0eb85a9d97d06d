"""Surface textures and UVs of the home's look (:mod:`sonicverse_core.scene.look`).

- **Textures** (:func:`atlas`): one tile per surface kind (wood planks, floor/wall tiles, painted plaster, fabric
  weave, brushed metal, veined stone, glazed ceramic, a sky view for windows, plain), made with numpy from seeded
  periodic noise, each tile padded by a wrapped gutter so its mipmaps (made by the GL driver) do not bleed into the
  next tile for the first ``log2(GUTTER)`` levels. The atlas is the same for every home (made once per process).
- **UVs** (:func:`tessellate`): a face is cut along a world (or object-local) grid of ``GRID`` m on the two axes of
  the plane it faces most, so each piece lies in one period of its texture: its UVs are the position within that
  period mapped into the kind's tile (an atlas cannot repeat by wrapping). The cut also gives the baked light
  vertices every ``GRID`` m on walls and floors.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

TILE = 256  # pixels per texture tile
GUTTER = 16  # wrapped border around each tile (mip levels 0-4 do not bleed)
CELL = TILE + 2 * GUTTER
ATLAS_COLS = 3
KINDS = ("plain", "wood", "tile", "plaster", "fabric", "metal", "stone", "sky", "ceramic")
#: metres per repeat of each tile (a multiple of GRID: every piece lies in one repeat)
PERIOD = {"plain": 1.0, "wood": 1.0, "tile": 1.0, "plaster": 1.0, "fabric": 1.0, "metal": 1.0, "stone": 1.0,
          "sky": 1.0, "ceramic": 1.0}
#: the cut's spacing (m): also the baked light's vertex spacing on large faces. 0.5 m doubled the apartment's
#: triangles (14k -> 26k) and cost ~30% of the 2 x 512^2 frame rate on llvmpipe (bench vr: ~140 -> ~100 stereo fps)
GRID = 1.0
TEXTURE_MEAN = 0.9  # the tiles' mean brightness (vertex colours are divided by it)

#: materials -> texture kind (a part's acoustic material decides what it looks like, so the eye and the ear agree)
MATERIAL_KIND = {"WoodPanel": "wood", "PlywoodPanel": "wood", "ParquetOnConcrete": "wood", "WoodCeiling": "wood",
                 "PolishedConcreteOrTile": "ceramic", "Marble": "stone", "LinoleumOnConcrete": "ceramic",
                 "CurtainHeavy": "fabric", "Metal": "metal", "GlassThin": "plain", "GlassThick": "plain",
                 "PlasterRough": "plaster", "PlasterSmooth": "plaster", "Sheetrock": "plaster",
                 "ConcreteBlockPainted": "plaster", "BrickPainted": "plaster", "AcousticCeilingTiles": "plaster",
                 "ConcreteBlockCoarse": "stone", "BrickBare": "stone", "FiberGlassInsulation": "fabric"}
#: categories whose look is fixed whatever their material
CATEGORY_KIND = {"window": "sky", "shower": "tile"}


# --- textures -----------------------------------------------------------------------------------------------------
def _noise(rng, sy: float, sx: float, n: int = TILE) -> np.ndarray:
    """Periodic smooth noise (n, n), zero mean, unit std: white noise through a Gaussian of sigma (sy, sx) px."""
    f = np.fft.fftfreq(n)
    h = np.exp(-2 * np.pi ** 2 * ((f[:, None] * sy) ** 2 + (f[None, :] * sx) ** 2))
    x = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * h))
    return (x - x.mean()) / (x.std() + 1e-12)


def _tile(kind: str) -> np.ndarray:
    """(TILE, TILE, 3) float in [0, 1]; row 0 is the top of the tile (v = 1), columns run along u."""
    rng = np.random.default_rng(list(KINDS).index(kind) + 101)
    T = TILE
    yy, xx = np.mgrid[0:T, 0:T]
    if kind == "wood":  # 4 boards of 0.25 m along u, grain along u, a seam between boards and one end joint each
        v = np.zeros((T, T))
        board = yy // (T // 4)
        grain = _noise(rng, 1.2, 60.0)
        rings = np.sin(2 * np.pi * (yy / 9.0 + 1.6 * _noise(rng, 6.0, 40.0)))
        tone = rng.uniform(-0.07, 0.07, 4)[board]
        v = 0.88 + 0.035 * grain + 0.03 * rings + tone
        v[(yy % (T // 4)) < 2] = 0.62
        joints = rng.integers(0, T, 4)
        v[np.abs(xx - joints[board]) < 1] = 0.66
        g = np.stack([v, v, v], -1)
    elif kind == "tile":  # 4 x 4 tiles of 0.25 m with grout
        v = 0.96 + 0.015 * _noise(rng, 8, 8) + rng.uniform(-0.025, 0.025, (4, 4))[yy // 64, xx // 64]
        grout = ((yy % 64) < 3) | ((xx % 64) < 3)
        v[grout] = 0.74
        g = np.stack([v, v, v], -1)
    elif kind == "plaster":
        v = 0.92 + 0.012 * _noise(rng, 1.5, 1.5) + 0.008 * _noise(rng, 24, 24)
        g = np.stack([v, v, v], -1)
    elif kind == "fabric":  # a weave of 4 px (16 mm) threads
        weave = np.sin(2 * np.pi * xx / 4) * np.sin(2 * np.pi * yy / 4)
        v = 0.88 + 0.05 * weave + 0.03 * _noise(rng, 1.5, 1.5) + 0.03 * _noise(rng, 30, 30)
        g = np.stack([v, v, v], -1)
    elif kind == "metal":  # brushed along u
        v = 0.89 + 0.05 * _noise(rng, 0.7, 80.0) + 0.02 * _noise(rng, 20, 20)
        g = np.stack([v, v, v], -1)
    elif kind == "stone":  # veined
        turb = np.sin(2 * np.pi * (xx / T * 2 + yy / T + 0.9 * _noise(rng, 18, 18)))
        v = 0.95 - 0.2 * (1 - np.abs(turb)) ** 12 + 0.02 * _noise(rng, 3, 3)
        g = np.stack([v, v, v], -1)
    elif kind == "ceramic":
        v = 0.93 + 0.015 * _noise(rng, 30, 30)
        g = np.stack([v, v, v], -1)
    elif kind == "sky":  # a view out: sky with clouds above, a far tree line and lawn below (colours, not shading)
        t = 1 - yy / (T - 1)  # 1 at the top
        sky = np.stack([0.50 + 0.2 * (1 - t), 0.68 + 0.12 * (1 - t), 0.93 + 0.0 * t], -1)
        cloud = np.clip((_noise(rng, 10, 28) - 0.4) * 0.9, 0, 1)[..., None] * np.clip((t[..., None] - 0.45) * 3, 0, 1)
        g = sky * (1 - cloud) + 0.97 * cloud
        horizon = 0.34 + 0.05 * _noise(rng, 4, 10)
        trees = t < horizon
        g[trees] = np.stack([0.22 + 0.06 * _noise(rng, 2, 2), 0.36 + 0.08 * _noise(rng, 2, 2),
                             0.20 + 0.04 * _noise(rng, 2, 2)], -1)[trees]
        lawn = t < 0.2
        g[lawn] = np.array([0.42, 0.58, 0.30])
        return np.clip(g, 0, 1)
    else:  # plain
        g = np.full((T, T, 3), TEXTURE_MEAN)
    g = np.clip(g, 0, 1)
    return g * (TEXTURE_MEAN / g.mean())  # every tile has the same mean: the vertex colour decides the brightness


@lru_cache(maxsize=1)
def atlas() -> tuple[np.ndarray, dict]:
    """(image (H, W, 4) uint8, {kind: (u0, v0, u1, v1)}): every kind's tile with a wrapped gutter, in one texture.
    UV (0, 0) is the image's bottom-left (OpenGL)."""
    rows = -(-len(KINDS) // ATLAS_COLS)
    W, H = ATLAS_COLS * CELL, rows * CELL
    img = np.zeros((H, W, 4), np.uint8)
    rects = {}
    for k, kind in enumerate(KINDS):
        r, c = divmod(k, ATLAS_COLS)
        t = np.clip(np.round(_tile(kind) * 255), 0, 255).astype(np.uint8)
        padded = np.pad(t, ((GUTTER, GUTTER), (GUTTER, GUTTER), (0, 0)), mode="edge" if kind == "sky" else "wrap")
        img[r * CELL:(r + 1) * CELL, c * CELL:(c + 1) * CELL, :3] = padded
        x0, y0 = c * CELL + GUTTER, r * CELL + GUTTER
        rects[kind] = (x0 / W, 1 - (y0 + TILE) / H, (x0 + TILE) / W, 1 - y0 / H)
    img[..., 3] = 255
    return img, rects


def atlas_bytes() -> int:
    """GPU memory of the atlas with its mipmaps (4/3 of the base level)."""
    img, _ = atlas()
    return int(img.nbytes * 4 // 3)


def kind_of(material: str, category: str = "") -> str:
    return CATEGORY_KIND.get(category) or MATERIAL_KIND.get(material, "plain")


# --- geometry: cut faces into pieces that lie in one texture period, with UVs ------------------------------------
_AXES = ((1, 2), (0, 2), (0, 1))


def _split(poly: list, ax: int, t: float) -> tuple[list, list]:
    lo, hi = [], []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        dp, dq = p[ax] - t, q[ax] - t
        if dp <= 0:
            lo.append(p)
        if dp >= 0:
            hi.append(p)
        if (dp < 0 < dq) or (dq < 0 < dp):
            x = p + (q - p) * (dp / (dp - dq))
            lo.append(x)
            hi.append(x)
    return lo, hi


def _cut(poly: list, ax: int, lines) -> list:
    out, cur = [], poly
    for t in lines:
        lo, hi = _split(cur, ax, t)
        if len(lo) >= 3:
            out.append(lo)
        cur = hi
        if len(cur) < 3:
            return out
    out.append(cur)
    return out


def tessellate(tri: np.ndarray, kinds: np.ndarray, uv_box: np.ndarray | None = None) -> tuple:
    """Cut triangles (n, 3, 3) at the ``GRID`` lines of the two axes of the plane each faces most; each piece gets
    UVs in its kind's atlas tile: the position within one texture period (``PERIOD``), or for 'sky' faces the
    position within ``uv_box[i]`` ((2, 3) bounds, the window). Returns (triangles (m, 3, 3), source face (m,),
    uv (m, 3, 2) in atlas coordinates)."""
    tri = np.asarray(tri, float)
    n = len(tri)
    if n == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros((0, 3, 2))
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dom = np.argmax(np.abs(nrm), axis=1)
    ab = np.array(_AXES)[dom]  # (n, 2)
    coords = np.stack([np.take_along_axis(tri, np.repeat(ab[:, None, k:k + 1], 3, 1), 2)[..., 0]
                       for k in range(2)], -1)  # (n, 3, 2) the two plane coordinates of each corner
    lo = np.floor(coords.min(1) / GRID + 1e-6)
    hi = np.floor(coords.max(1) / GRID - 1e-6)
    sky = np.array([k == "sky" for k in kinds], bool)
    simple = np.all(lo >= hi, axis=1) | sky
    out_tri, out_src = [tri[simple]], [np.nonzero(simple)[0]]
    extra_t, extra_s = [], []
    for i in np.nonzero(~simple)[0]:
        a, b = ab[i]
        pieces = [[tri[i, 0], tri[i, 1], tri[i, 2]]]
        for ax, k in ((a, 0), (b, 1)):
            lines = np.arange(lo[i, k] + 1, hi[i, k] + 1) * GRID
            if len(lines):
                pieces = [q for p in pieces for q in _cut(p, ax, lines)]
        for p in pieces:
            for j in range(1, len(p) - 1):
                t = np.array([p[0], p[j], p[j + 1]])
                if np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) > 1e-10:
                    extra_t.append(t)
                    extra_s.append(i)
    if extra_t:
        out_tri.append(np.array(extra_t))
        out_src.append(np.array(extra_s, np.int64))
    T = np.concatenate(out_tri)
    S = np.concatenate(out_src)
    # UVs: position within one period (the piece's centroid picks the period), mapped into the kind's tile
    ab_s = ab[S]
    c = np.stack([np.take_along_axis(T, np.repeat(ab_s[:, None, k:k + 1], 3, 1), 2)[..., 0] for k in range(2)], -1)
    per = np.array([PERIOD[kinds[s]] for s in S])[:, None, None]
    local = c / per - np.floor(c.mean(1, keepdims=True) / per)
    sky_s = sky[S]
    if sky_s.any() and uv_box is not None:
        box = uv_box[S[sky_s]]  # (k, 2, 3)
        blo = np.take_along_axis(box[:, 0], ab_s[sky_s], 1)[:, None, :]
        bhi = np.take_along_axis(box[:, 1], ab_s[sky_s], 1)[:, None, :]
        local[sky_s] = (c[sky_s] - blo) / np.maximum(bhi - blo, 1e-9)
    local = np.clip(local, 0.0, 1.0)
    _, rects = atlas()
    r = np.array([rects[kinds[s]] for s in S])  # (m, 4)
    uv = np.empty_like(local)
    uv[..., 0] = r[:, None, 0] + local[..., 0] * (r[:, None, 2] - r[:, None, 0])
    uv[..., 1] = r[:, None, 1] + local[..., 1] * (r[:, None, 3] - r[:, None, 1])
    return T, S, uv
