"""The look of a home, baked once per home and cached: procedural surface textures in one atlas, UVs on every face,
and light (per-room ceiling lamps, window daylight, ambient occlusion) baked into the vertex colours.

Drawn with pyrender's cheap FLAT shader (texture x vertex colour, no per-pixel lighting), so a CPU keeps its frame
rate: one primitive per merged group, one texture for the whole home.

- **Textures and UVs** (:mod:`sonicverse_core.scene.textures`): one atlas of procedural tiles; faces cut on a
  grid so each piece has UVs in one repeat of its tile.
- **Light** (:func:`bake_light`): per vertex (each position and normal once), in linear units where 1 is a floor
  under a lamp: ``ambient * (a + (1 - a) * AO)`` (AO: the share of cosine-weighted rays that leave within
  ``AO_DISTANCE``), plus a lamp at each room's ceiling (inverse square, Lambert, shadowed), plus daylight through
  each window (the window sampled as small area lights, shadowed). Shadows and occlusion come from the static
  structure and the furniture at rest (Embree). The result is clipped to ``[0, E_MAX]``: finite and in range.
- **Colours**: albedo (a part's colour; walls painted per room, chosen by the home's seed) in linear light times
  the irradiance, back to sRGB, divided by the texture's mean so the textured surface keeps the albedo's brightness.

What moves keeps the light it had at rest (a door swinging carries its shading); bodies that are not part of the
home (the avatar, robots, the simulated person) use the directional bake of :mod:`app.scene.visual` at the same
ambient level. ``HomeLook`` is cached in memory on the scene and on disk (``cache_dir()/looks``) keyed by the
structure, the furniture and ``LOOK_VERSION``.
"""
from __future__ import annotations

import hashlib
import re
import time

import numpy as np

from sonicverse_core.scene.textures import (  # noqa: F401  (re-exported: the look's textures and UVs)
    ATLAS_COLS, CATEGORY_KIND, CELL, GRID, GUTTER, KINDS, MATERIAL_KIND, PERIOD, TEXTURE_MEAN, TILE, atlas, atlas_bytes,
    kind_of, tessellate)

LOOK_VERSION = 6
AO_RAYS, AO_DISTANCE, AO_FLOOR = 16, 0.6, 0.3
AMBIENT = 0.32  # linear irradiance of the indirect light where nothing occludes
LAMP_POWER = 4.5  # a lamp's intensity: E = LAMP_POWER cos / d^2 (a floor 2.2 m below: ~0.9)
LAMP_DROP = 0.45  # a pendant lamp hangs this far below the ceiling
DAYLIGHT = 2.2  # a window's radiance (E = DAYLIGHT * A cos cos / (pi d^2))
E_MAX = 1.4

#: colours of the static structure by part category (a home's paint, ceiling, floor, windows)
STRUCTURE_COLOURS = {"wall": (228, 221, 207, 255), "ceiling": (246, 246, 243, 255), "floor": (168, 126, 86, 255),
                     "threshold": (150, 110, 76, 255), "window": (176, 208, 232, 255)}
#: paints of a home's rooms (walls), chosen per room by the home's seed; wet rooms are tiled white
PAINTS = ((236, 230, 218), (200, 212, 192), (198, 214, 226), (228, 212, 186), (234, 212, 204), (214, 214, 210),
          (240, 236, 226), (222, 206, 222))
WET_ROOMS = {"bathroom": (236, 238, 238), "kitchen": (238, 236, 230)}


def palette(n: int, seed: int = 7) -> np.ndarray:
    """A fixed RGBA uint8 colour per index."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(90, 230, (max(n, 1), 4)).astype(np.uint8)
    c[:, 3] = 255
    return c


def part_category(name: str) -> str:
    """A structure part's semantic category from its name: trailing numbers dropped ('wall_2_1' -> 'wall',
    'Window.003' -> 'window'), the first word kept ('floor bathroom' -> 'floor'); lower case."""
    if re.fullmatch(r"[xy][01]", name):  # a shoebox's walls
        return "wall"
    base = re.sub(r"([_.\-\s]*\d+)+$", "", name).strip().lower()
    return base.split()[0] if base else "structure"  # 'floor bathroom' -> 'floor'


# --- light --------------------------------------------------------------------------------------------------------
def _srgb_to_linear(c):
    return np.asarray(c, float) ** 2.2


def _linear_to_srgb(c):
    return np.clip(c, 0, 1) ** (1 / 2.2)


def lamps(scene) -> np.ndarray:
    """(k, 3) one pendant lamp per room (the footprint's centroid, LAMP_DROP below the ceiling); a scene without
    rooms gets one at the middle of its bounds."""
    out = []
    for r in scene.rooms:
        fp = np.asarray(r.footprint, float)
        xy = fp.mean(0)
        if not r.contains(xy)[0]:  # an L-shaped room: the footprint point nearest its centroid
            xy = fp[np.argmin(np.linalg.norm(fp - xy, axis=1))] * 0.9 + xy * 0.1
        out.append((xy[0], xy[1], r.z_ceiling - LAMP_DROP))
    if not out:
        b = scene.bounds
        out.append(((b[0, 0] + b[1, 0]) / 2, (b[0, 1] + b[1, 1]) / 2, b[1, 2] - LAMP_DROP))
    return np.array(out, float)


def window_samples(scene, per_m: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Window area lights: (points (k, 3), normals (k, 3) (either side), areas (k,)), a few per window part."""
    sm = scene.static_mesh()
    pts, nrm, area = [], [], []
    for pi, name in enumerate(sm.part_names):
        if part_category(name) != "window":
            continue
        f = sm.faces[sm.face_part == pi]
        v = sm.vertices[np.unique(f)]
        lo, hi = v.min(0), v.max(0)
        ext = hi - lo
        thin = int(np.argmin(ext))
        a, b = [k for k in range(3) if k != thin]
        na, nb = max(1, int(round(ext[a] * per_m))), max(1, int(round(ext[b] * per_m)))
        for i in range(na):
            for j in range(nb):
                p = (lo + hi) / 2
                p = p.copy()
                p[a] = lo[a] + (i + 0.5) * ext[a] / na
                p[b] = lo[b] + (j + 0.5) * ext[b] / nb
                n = np.zeros(3)
                n[thin] = 1.0
                pts.append(p)
                nrm.append(n)
                area.append(ext[a] * ext[b] / (na * nb))
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    return np.array(pts), np.array(nrm), np.array(area)


def _visible(caster, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether segment a -> b (each (n, 3)) is free (the last 2 cm before b not tested: a lamp or a window)."""
    d = b - a
    L = np.linalg.norm(d, axis=1)
    ok = L > 1e-6
    out = np.ones(len(a), bool)
    if caster.empty or not ok.any():
        return out
    face, dist = caster.faces(a[ok], d[ok] / L[ok, None], np.maximum(L[ok] - 0.02, 1e-4))
    out[ok] = face < 0
    return out


def bake_light(scene, points: np.ndarray, normals: np.ndarray, caster, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) linear irradiance (RGB: warm lamps, cool daylight) at points with unit normals, in [0, E_MAX]; NaN
    for points inside a solid (most ambient-occlusion rays meet the backs of faces)."""
    n = len(points)
    E = np.zeros((n, 3))
    if n == 0:
        return E
    o = points + normals * 2e-3
    # ambient occlusion: cosine-weighted hemisphere rays (the same directions for every point, rotated to it)
    u1, u2 = rng.random(AO_RAYS), rng.random(AO_RAYS)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, np.array([[0, 0, 1.0]]), np.array([[1.0, 0, 0]]))
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    dirs = (local[None, :, 0:1] * t1[:, None] + local[None, :, 1:2] * t2[:, None] + local[None, :, 2:3] *
            normals[:, None]).reshape(-1, 3)
    inside = np.zeros(n, bool)
    if caster.empty:
        ao = np.ones(n)
    else:
        face, _ = caster.faces(np.repeat(o, AO_RAYS, 0), dirs, np.full(len(dirs), AO_DISTANCE))
        ao = (face < 0).reshape(n, AO_RAYS).mean(1)
        # a vertex inside a solid (a wall's end hidden in the wall it meets) sees the backs of faces
        back = (face >= 0) & (np.einsum("ij,ij->i", caster.normals[np.maximum(face, 0)], dirs) > 0)
        inside = back.reshape(n, AO_RAYS).mean(1) >= 0.5
    E += (AMBIENT * (AO_FLOOR + (1 - AO_FLOOR) * ao))[:, None] * np.array([1.0, 0.98, 0.95])
    # lamps: inverse square, Lambert, shadowed
    warm = np.array([1.0, 0.9, 0.75])
    for lamp in lamps(scene):
        d = lamp - o
        L = np.maximum(np.linalg.norm(d, axis=1), 0.3)
        cos = np.einsum("ij,ij->i", normals, d) / L
        idx = np.nonzero(cos > 0)[0]
        if not len(idx):
            continue
        vis = _visible(caster, o[idx], np.repeat(lamp[None], len(idx), 0))
        E[idx[vis]] += (LAMP_POWER * cos[idx[vis]] / L[idx[vis]] ** 2)[:, None] * warm
    # daylight through windows: small area lights
    wp, wn, wa = window_samples(scene)
    cool = np.array([0.85, 0.93, 1.0])
    for p, nw, a in zip(wp, wn, wa):
        d = p - o
        L = np.maximum(np.linalg.norm(d, axis=1), 0.25)
        cos_p = np.einsum("ij,ij->i", normals, d) / L
        cos_w = np.abs(d @ nw) / L
        idx = np.nonzero((cos_p > 0) & (L < 12.0))[0]
        if not len(idx):
            continue
        vis = _visible(caster, o[idx], np.repeat(p[None], len(idx), 0))
        k = idx[vis]
        E[k] += (DAYLIGHT * a * cos_p[k] * cos_w[k] / (np.pi * L[k] ** 2))[:, None] * cool
    E = np.clip(np.nan_to_num(E, nan=0.0, posinf=E_MAX), 0.0, E_MAX)
    E[inside] = np.nan  # filled from the visible corners of each triangle (:func:`fill_hidden`)
    return E


def fill_hidden(E: np.ndarray) -> np.ndarray:
    """Corners (3 per triangle, (3m, 3)) whose light is NaN (inside a solid) take the mean of their triangle's
    other corners (0 where all three are hidden): a visible piece does not darken towards a corner it hides."""
    c = E.reshape(-1, 3, 3)
    bad = np.isnan(c[..., 0])
    good = ~bad
    cnt = good.sum(1)
    mean = np.where(cnt[:, None] > 0, np.nansum(np.where(good[..., None], c, 0), 1) / np.maximum(cnt, 1)[:, None], 0)
    c = np.where(bad[..., None], mean[:, None, :], c)
    return c.reshape(-1, 3)


def shade(albedo: np.ndarray, E: np.ndarray) -> np.ndarray:
    """RGBA float vertex colours in [0, 1]: sRGB albedo (n, 3|4) uint8 lit by linear irradiance E (n, 3), divided by
    the texture's mean brightness."""
    lin = _srgb_to_linear(np.asarray(albedo, float)[:, :3] / 255.0) * E
    out = np.ones((len(lin), 4))
    out[:, :3] = np.clip(_linear_to_srgb(lin) / TEXTURE_MEAN, 0.0, 1.0)
    return out


LIGHT_DIR = np.array([0.35, 0.5, 0.79])  # towards the light (unit), from above


def bake_lighting(colours: np.ndarray, normals: np.ndarray, ambient: float = 0.45) -> np.ndarray:
    """RGBA uint8 (n, 4) face colours lit by one directional light: c * (ambient + (1 - ambient) * |n . l|) (two-
    sided, like the interior faces a camera sees)."""
    k = ambient + (1 - ambient) * np.abs(normals @ LIGHT_DIR / np.linalg.norm(LIGHT_DIR))
    out = colours.astype(np.float32).copy()
    out[:, :3] *= k[:, None]
    return np.clip(out, 0, 255).astype(np.uint8)


# --- a home's look ------------------------------------------------------------------------------------------------
def _room_paints(scene) -> dict:
    seed = int(scene.metadata.get("seed", 0)) if isinstance(scene.metadata.get("seed", 0), (int, np.integer)) else 0
    rng = np.random.default_rng([seed, 0x9A1E7])
    out = {}
    for r in scene.rooms:
        paint = WET_ROOMS.get(r.type) or PAINTS[int(rng.integers(len(PAINTS)))]
        out[r.name] = tuple(paint) + (255,)
    return out


def static_albedo(scene) -> tuple[np.ndarray, list]:
    """((faces, 4) uint8 albedo of the static structure, kinds per face): walls in the default paint (see
    :func:`paint_walls`), ceilings white, floors wood, windows the sky; other parts by material."""
    from sonicverse_core.scene.materials import MATERIAL_NAMES

    sm = scene.static_mesh()
    mat_pal = palette(len(MATERIAL_NAMES))
    cats = [part_category(n) for n in sm.part_names]
    per_part = np.array([STRUCTURE_COLOURS.get(c, (0, 0, 0, 0)) for c in cats] or np.zeros((0, 4)),
                        np.uint8).reshape(-1, 4)
    cols = mat_pal[sm.face_material].copy()
    known = per_part[sm.face_part, 3] > 0
    cols[known] = per_part[sm.face_part[known]]
    kinds = [kind_of(MATERIAL_NAMES[m], cats[p]) for m, p in zip(sm.face_material, sm.face_part)]
    return cols, kinds


def paint_walls(scene, tri: np.ndarray, src: np.ndarray, cols: np.ndarray) -> None:
    """Paint the wall pieces ``tri`` (cut from static faces ``src``) in the colour of the room each looks into (a
    corridor's long wall takes each room's paint where it faces it; pieces of overlapping coplanar walls get the same
    colour, so their depth fight does not show)."""
    if not scene.rooms or not len(tri):
        return
    sm = scene.static_mesh()
    wall = np.array([part_category(n) == "wall" for n in sm.part_names], bool)
    idx = np.nonzero(wall[sm.face_part[src]])[0]
    if not len(idx):
        return
    probe = tri[idx].mean(1)[:, :2] + _unit_normals(tri[idx])[:, :2] * 0.08
    paints = _room_paints(scene)
    for r in scene.rooms:
        cols[idx[r.contains(probe)]] = paints[r.name]


# --- trim: skirting boards, door and window frames (seen, not heard: below the acoustic engine's resolution) ------
SKIRTING_H, SKIRTING_T = 0.08, 0.012
FRAME_W, FRAME_T = 0.07, 0.015
TRIM_COLOUR = (242, 240, 234, 255)


def _box(lo, hi):
    import trimesh

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _part_boxes(scene, category: str) -> list[np.ndarray]:
    sm = scene.static_mesh()
    out = []
    for pi, name in enumerate(sm.part_names):
        if part_category(name) == category:
            v = sm.vertices[np.unique(sm.faces[sm.face_part == pi])]
            out.append(np.array([v.min(0), v.max(0)]))
    return out


def _wall_depth(caster, p: np.ndarray, normal: np.ndarray, default: float) -> float:
    """Distance from a point inside a wall to its face along ``normal`` (``default`` if nothing is met)."""
    if caster is None or caster.empty:
        return default
    f, d = caster.faces(p[None], normal[None], np.array([1.0]))
    return float(d[0]) if f[0] >= 0 else default


def trim(scene, caster=None) -> list:
    """The home's trim as (name, world mesh) boxes: skirting boards along each room's walls (broken at door
    openings), frames round both faces of each door opening (thresholds) and each window, and window sills (1 cm
    above the opening's sill: no face of the trim is coplanar with a face of the structure in sight)."""
    out = []
    doors = [b for b in _part_boxes(scene, "threshold")]
    for r in scene.rooms:
        fp = np.asarray(r.footprint, float)
        ccw = np.sum(fp[:, 0] * np.roll(fp[:, 1], -1) - np.roll(fp[:, 0], -1) * fp[:, 1]) > 0
        for i in range(len(fp)):
            p, q = fp[i], fp[(i + 1) % len(fp)]
            L = np.linalg.norm(q - p)
            if L < 0.05:
                continue
            d = (q - p) / L
            inward = np.array([-d[1], d[0]]) * (1 if ccw else -1)
            cuts = []  # door openings on this edge: (t0, t1) along it
            for b in doors:
                c = (b[0, :2] + b[1, :2]) / 2
                ext = b[1, :2] - b[0, :2]
                thin = int(np.argmin(ext))
                if abs(d[thin]) > 0.5 or abs((c - p) @ inward) > ext[thin] / 2 + 0.02:
                    continue
                t = sorted(((b[0, :2] - p) @ d, (b[1, :2] - p) @ d))
                cuts.append((t[0], t[1]))
            spans, t0 = [], 0.0
            for a, b in sorted(cuts):
                if a > t0:
                    spans.append((t0, min(a, L)))
                t0 = max(t0, b)
            if t0 < L:
                spans.append((t0, L))
            for k, (a, b) in enumerate(spans):
                if b - a < 0.03:
                    continue
                corners = np.array([p + d * a, p + d * b, p + d * a + inward * SKIRTING_T, p + d * b + inward * SKIRTING_T])
                lo = np.append(corners.min(0), r.z_floor + 0.001)
                hi = np.append(corners.max(0), r.z_floor + SKIRTING_H)
                out.append((f"skirting {r.name} {i}.{k}", _box(lo, hi)))
    for j, b in enumerate(doors):  # door frames: jambs and a head on each face of the wall
        ext = b[1] - b[0]
        thin = int(np.argmin(ext[:2]))
        along = 1 - thin
        c = (b[0] + b[1]) / 2
        up = np.zeros(3)
        up[2] = 1.0
        top = _wall_depth(caster, np.array([c[0], c[1], b[0, 2] + 1.0]), up, 1.05) + b[0, 2] + 1.0
        a0, a1 = b[0, along], b[1, along]
        for side, face in ((-1, b[0, thin]), (1, b[1, thin])):
            f0, f1 = sorted((face, face + side * FRAME_T))
            for lo_a, hi_a, z0, z1 in ((a0 - FRAME_W, a0, b[0, 2], top + FRAME_W), (a1, a1 + FRAME_W, b[0, 2],
                                                                                        top + FRAME_W),
                                       (a0 - FRAME_W, a1 + FRAME_W, top, top + FRAME_W)):
                lo, hi = np.zeros(3), np.zeros(3)
                lo[along], hi[along], lo[thin], hi[thin], lo[2], hi[2] = lo_a, hi_a, f0, f1, z0, z1
                out.append((f"door frame {j}", _box(lo, hi)))
    for j, b in enumerate(_part_boxes(scene, "window")):  # window frames on both faces, and sills
        ext = b[1] - b[0]
        thin = int(np.argmin(ext))
        if thin == 2:
            continue  # a skylight: no frame
        along = 1 - thin
        c = (b[0] + b[1]) / 2
        n = np.zeros(3)
        n[thin] = 1.0
        below = c.copy()
        below[2] = b[0, 2] - 0.1
        half = _wall_depth(caster, below, n, 0.06) if b[0, 2] > 0.15 else 0.06
        a0, a1, z0, z1 = b[0, along], b[1, along], b[0, 2], b[1, 2]
        for side in (-1, 1):
            face = c[thin] + side * half
            f0, f1 = sorted((face, face + side * FRAME_T))
            s0, s1 = sorted((face - side * half, face + side * 0.05))
            for lo_a, hi_a, lz, hz, t0, t1 in ((a0 - 0.05, a0, z0 - 0.03, z1 + 0.05, f0, f1),
                                               (a1, a1 + 0.05, z0 - 0.03, z1 + 0.05, f0, f1),
                                               (a0 - 0.05, a1 + 0.05, z1, z1 + 0.05, f0, f1),
                                               (a0 - 0.07, a1 + 0.07, z0 - 0.03, z0 + 0.01, s0, s1)):
                lo, hi = np.zeros(3), np.zeros(3)
                lo[along], hi[along], lo[thin], hi[thin], lo[2], hi[2] = lo_a, hi_a, t0, t1, lz, hz
                out.append((f"window frame {j}", _box(lo, hi)))
    return out


def _caster(scene):
    from sonicverse_core.geometry.raycast import RayCaster
    from sonicverse_core.scene.model import SceneMesh

    s, d = scene.static_mesh(), scene.dynamic_mesh()
    mesh = SceneMesh(np.concatenate([s.vertices, d.vertices]), np.concatenate([s.faces, d.faces + len(s.vertices)]),
                     np.concatenate([s.face_material, d.face_material]), np.concatenate([s.face_part, d.face_part]),
                     s.part_names + d.part_names)
    return RayCaster(mesh)


def _unit_normals(tri: np.ndarray) -> np.ndarray:
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


class HomeLook:
    """A home's baked look. ``static``: dict of per-vertex arrays of the structure and its trim (three vertices per
    triangle): 'pos' (k, 3), 'nrm' (k, 3), 'uv' (k, 2), 'col' (k, 4) float32, and 'face' (k/3,) the static face each
    triangle came from (-1: trim); 'alb' (k, 4) the albedo alone (the lit path's vertex colours). ``objects``: name -> the same arrays of the object's parts in its local frame, lit where it stood when
    the home was baked. ``bake_s``: seconds it took (0 when loaded from the cache)."""

    def __init__(self, static: dict, objects: dict, bake_s: float = 0.0, cached: bool = False):
        self.static, self.objects, self.bake_s, self.cached = static, objects, bake_s, cached

    @property
    def triangles(self) -> int:
        return (len(self.static["pos"]) + sum(len(o["pos"]) for o in self.objects.values())) // 3

    @property
    def vertex_bytes(self) -> int:
        """Bytes of the vertex buffers pyrender uploads (position, normal, uv, colour: 48 per vertex; one colour set
        is drawn: the baked one, or the albedo on the lit path)."""
        return self.triangles * 3 * 48

    @property
    def texture_bytes(self) -> int:
        return atlas_bytes()


def _object_key(o) -> bytes:
    h = hashlib.sha256(o.name.encode())
    h.update(np.round(o.pose, 5).tobytes())
    for name, mat, m, col in o.looks():
        h.update(f"{name}|{mat}|{col}".encode())
        h.update(np.round(np.asarray(m.vertices), 5).tobytes())
        h.update(np.asarray(m.faces, np.int64).tobytes())
    return h.digest()


def look_key(scene) -> str:
    h = hashlib.sha256(f"look v{LOOK_VERSION} T{TILE} G{GRID}".encode())
    h.update(scene.static_hash().encode())
    h.update(repr(sorted(_room_paints(scene).items())).encode())
    for r in scene.rooms:
        h.update(f"{r.name}|{r.type}|{r.z_ceiling}".encode())
        h.update(np.asarray(r.footprint, float).tobytes())
    for o in scene.objects:
        h.update(_object_key(o))
    return h.hexdigest()[:32]


def bake(scene, seed: int = 0) -> HomeLook:
    """Bake a home's look now (no cache): textures' UVs and the light at every vertex."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    caster = _caster(scene)
    sm = scene.static_mesh()
    albedo, kinds = static_albedo(scene)
    boxes = np.zeros((len(sm.part_names), 2, 3))
    for pi in range(len(sm.part_names)):
        v = sm.vertices[np.unique(sm.faces[sm.face_part == pi])] if np.any(sm.face_part == pi) else np.zeros((1, 3))
        boxes[pi] = v.min(0), v.max(0)
    T, S, uv = tessellate(sm.vertices[sm.faces], np.array(kinds, object), boxes[sm.face_part])
    alb = albedo[S]
    paint_walls(scene, T, S, alb)
    sky = np.array([k == "sky" for k in kinds], bool)[S]
    pieces = trim(scene, caster)
    if pieces:  # trim joins the structure (face -1: drawn with the rooms' common group)
        tt = np.concatenate([np.asarray(m.vertices, float)[np.asarray(m.faces)] for _, m in pieces])
        Tt, St, uvt = tessellate(tt, np.array(["plain"] * len(tt), object))
        T, uv = np.concatenate([T, Tt]), np.concatenate([uv, uvt])
        S = np.concatenate([S, np.full(len(St), -1)])
        alb = np.concatenate([alb, np.tile(np.array(TRIM_COLOUR, np.uint8), (len(St), 1))])
        sky = np.concatenate([sky, np.zeros(len(St), bool)])
    groups = [("static", T, S, uv, alb, sky)]
    cats = sorted({o.category for o in scene.objects})
    cpal = palette(len(cats), seed=11)
    for o in scene.objects:
        looks = o.looks()
        tris, cols, ks = [], [], []
        for _, mat, m, col in looks:
            tris.append(np.asarray(m.vertices, float)[np.asarray(m.faces)])
            c = col if col is not None else cpal[cats.index(o.category)]
            cols.append(np.tile(np.asarray(c, np.uint8)[:4], (len(m.faces), 1)))
            ks += [kind_of(mat, o.category)] * len(m.faces)
        tri = np.concatenate(tris)
        To, So, uvo = tessellate(tri, np.array(ks, object))
        groups.append((o.name, To, So, uvo, np.concatenate(cols)[So], np.zeros(len(So), bool)))
    # light every distinct (world position, normal) once
    world, wnrm, spans = [], [], []
    for name, Tg, _, _, _, _ in groups:
        if name == "static":
            W = Tg
        else:
            pose = scene.object(name).pose
            W = Tg @ pose[:3, :3].T + pose[:3, 3]
        n = np.repeat(_unit_normals(W)[:, None], 3, 1)
        world.append(W.reshape(-1, 3))
        wnrm.append(n.reshape(-1, 3))
        spans.append(len(W) * 3)
    P, N = np.concatenate(world), np.concatenate(wnrm)
    key = np.concatenate([np.round(P / 1e-4), np.round(N * 1e3)], 1).astype(np.int64)
    uniq, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    E = fill_hidden(bake_light(scene, P[first], N[first], caster, rng)[inv.reshape(-1)])
    static, objects, off = {}, {}, 0
    for (name, Tg, Sg, uvg, alb, sky), k in zip(groups, spans):
        col = shade(np.repeat(alb, 3, 0), E[off:off + k])
        base = np.ones((k, 4))  # the albedo alone, for the lit (PBR) path
        base[:, :3] = np.clip(np.repeat(alb, 3, 0)[:, :3] / 255.0 / TEXTURE_MEAN, 0, 1)
        if sky.any():  # a window shows the view out as it is (not lit by the room)
            col[np.repeat(sky, 3)] = 1.0
            base[np.repeat(sky, 3)] = 1.0
        arrays = {"pos": Tg.reshape(-1, 3).astype(np.float32), "nrm": np.repeat(_unit_normals(Tg), 3, 0)
                  .astype(np.float32), "uv": uvg.reshape(-1, 2).astype(np.float32), "col": col.astype(np.float32),
                  "alb": base.astype(np.float32), "face": Sg.astype(np.int64)}
        off += k
        if name == "static":
            static = arrays
        else:
            objects[name] = arrays
    return HomeLook(static, objects, time.perf_counter() - t0)


def home_look(scene, cache: bool = True) -> HomeLook:
    """The scene's look: from memory, else from the disk cache, else baked (and cached)."""
    key = look_key(scene)
    held = getattr(scene, "_home_look", None)
    if held is not None and held[0] == key:
        return held[1]
    look = None
    path = None
    if cache:
        from assets_manifest import cache_dir

        path = cache_dir() / "looks" / f"{key}.npz"
        if path.exists():
            try:
                look = _load(path, scene)
            except Exception:  # a damaged cache entry is baked again (and replaced)
                look = None
    if look is None:
        look = bake(scene)
        if path is not None:
            _save(path, look)
    scene._home_look = (key, look)
    return look


def _save(path, look: HomeLook) -> None:
    from sonicverse_core.storage import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    flat = {f"static/{k}": v for k, v in look.static.items()}
    names = list(look.objects)
    flat["names"] = np.array(names, dtype=str)
    for i, name in enumerate(names):
        flat.update({f"obj/{i}/{k}": v for k, v in look.objects[name].items()})
    with atomic_write(path) as f:
        np.savez(f, **flat)


def _load(path, scene) -> HomeLook:
    with np.load(path) as z:
        static = {k.split("/", 1)[1]: z[k] for k in z.files if k.startswith("static/")}
        names = [str(n) for n in z["names"]]
        objects: dict = {n: {} for n in names}
        for k in z.files:
            if k.startswith("obj/"):
                _, i, field = k.split("/", 2)
                objects[names[int(i)]][field] = z[k]
    if set(objects) != {o.name for o in scene.objects} or set(static) != {"pos", "nrm", "uv", "col", "alb", "face"}:
        raise ValueError("cache entry does not match the scene")
    return HomeLook(static, objects, 0.0, cached=True)
