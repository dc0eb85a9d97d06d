"""Reverb probes baked by ray tracing over a scene's static structure.

From each probe, ``rays`` rays leave uniformly and bounce with per-band energy losses (absorption of every surface hit, air absorption along the path). The
ensemble's energy in flight gives the room's energy decay per band; Schroeder backward integration of that curve,
fitted between -5 and -35 dB (T30; -5..-25 dB when the range is short), gives RT60, and 0..-10 dB gives the early
decay time. How a bounce scatters is :attr:`BakeConfig.scattering`:

- ``"stochastic"`` (default): the ray leaves in a Lambertian direction with the material's scattering coefficient as
  probability, else specularly. A fraction s of the reflected energy is scattered, as ISO 17497-1 defines s. In a
  diffuse shoebox the decay matches Eyring within 2% (tests/test_acoustics.py).
- ``"vector"``: every bounce leaves along the normalised blend s * (a Lambertian direction) + (1 - s) * (the
  specular one). This is "vector-based scattering", as in pyroomacoustics' ray tracer. A small s bends each ray a
  little at every bounce, so the field stays non-diffuse much longer: rooms with one absorbing surface ring longer,
  and uniform rooms decay faster than Eyring because rays lean towards the normals. `bench fidelity --scattering
  vector` shows that this model, not the tracer, is where our T30 and the peer's part.

A proxy box (distances to the nearest surfaces along +-x, +-y, +-z and their materials) serves the early
reflections (median distances in a cone of rays per axis, robust to doors). Bakes are cached on disk keyed by the static structure's content hash, the probe positions and the
settings.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass


import numpy as np

from sonicverse_core.errors import ConfigError
from sonicverse_core.scene.materials import BANDS, MATERIAL_NAMES, material_arrays

SPEED_OF_SOUND = 343.0
#: air absorption m (1/m, energy) per band, Resonance Audio's values
AIR_ABSORPTION = np.array([0.0006, 0.0006, 0.0007, 0.0008, 0.0010, 0.0015, 0.0026, 0.0060, 0.0207])
RT60_MAX = 60.0
SCATTERING = ("stochastic", "vector")


@dataclass(frozen=True)
class BakeConfig:
    """rays per probe; max_bounces; max_time (s) of tracing; hist_dt (s) of the decay histogram; seed;
    scattering: "stochastic" or "vector" (the module's docstring); per_room: a probe in one of the scene's rooms
    bakes that room's own decay (rays that leave it through an opening are lost to it) and the renderer couples
    the rooms' decays (``coupling.RoomCoupling.late_split``; the default since session 27: a dead room beside a
    live one keeps its own decay); off: each probe bakes the decay of the whole connected space around it (one
    decay everywhere, as before); min_scattering: every material scatters at least this much (0, the default, keeps
    the table's; at 1 every bounce is Lambertian in either model: ``bench fidelity --min-scattering 1`` compares
    the rest of two models without their scattering models)."""

    rays: int = 2000
    max_bounces: int = 400
    max_time: float = 4.0
    hist_dt: float = 0.002
    seed: int = 0
    scattering: str = "stochastic"
    per_room: bool = True
    min_scattering: float = 0.0

    def __post_init__(self):
        if not (16 <= self.rays <= 10_000_000):
            raise ConfigError(f"rays per probe must be within 16..1e7, got {self.rays}")
        if not (1 <= self.max_bounces <= 100_000) or not (0.05 <= self.max_time <= 60):
            raise ConfigError("max_bounces must be 1..1e5 and max_time 0.05..60 s")
        if self.scattering not in SCATTERING:
            raise ConfigError(f"unknown scattering model '{self.scattering}'; use one of {', '.join(SCATTERING)}")
        if not (0.0 <= self.min_scattering <= 1.0):
            raise ConfigError(f"min_scattering must be within 0..1, got {self.min_scattering}")


@dataclass
class Probe:
    """position (3,); rt60, edt (9,) seconds; box_lo, box_hi (3,) proxy box; box_materials: 6 names
    (-x, +x, -y, +y, -z, +z); volume (m^3) and mean absorption (9,) of the proxy box."""

    position: np.ndarray
    rt60: np.ndarray
    edt: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_materials: tuple
    enclosed: float  # fraction of rays that hit something (1: closed room)
    room: str | None = None  # the room whose own decay it baked (rays leaving it were lost); None: the whole space

    @property
    def volume(self) -> float:
        return float(np.prod(self.box_hi - self.box_lo))

    def stored(self) -> "Probe":
        """The probe as the bake cache keeps it (its numbers rounded as :meth:`to_json` rounds them)."""
        d = self.to_json()
        return Probe(*(np.asarray(d[k], np.float64) for k in ("position", "rt60", "edt", "box_lo", "box_hi")),
                     tuple(d["box_materials"]), float(d["enclosed"]), d["room"])

    def to_json(self) -> dict:
        return {"position": np.round(self.position, 4).tolist(), "rt60": np.round(self.rt60, 4).tolist(),
                "edt": np.round(self.edt, 4).tolist(), "box_lo": np.round(self.box_lo, 4).tolist(),
                "box_hi": np.round(self.box_hi, 4).tolist(), "box_materials": list(self.box_materials),
                "enclosed": round(self.enclosed, 4), "room": self.room}


def _uniform_dirs(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _lambert(rng, normals):
    """Cosine-weighted directions around unit normals (n, 3)."""
    n = len(normals)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], 1)
    a = np.where(np.abs(normals[:, :1]) > 0.9, np.array([[0.0, 1, 0]]), np.array([[1.0, 0, 0]]))
    t = np.cross(normals, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normals, t)
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * normals


def decay_times(energy: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """RT60 and EDT (s) per band from energy-in-flight curves (bands, T) by Schroeder integration."""
    rt, edt = np.full(len(energy), RT60_MAX), np.full(len(energy), RT60_MAX)
    t = (np.arange(energy.shape[1]) + 0.5) * dt
    for b, e in enumerate(energy):
        sch = np.cumsum(e[::-1])[::-1]
        if sch[0] <= 0:
            rt[b] = edt[b] = 0.0
            continue
        db = 10 * np.log10(np.maximum(sch / sch[0], 1e-30))

        def fit(lo, hi):
            m = (db <= lo) & (db >= hi)
            if np.count_nonzero(m) < 3:
                return None
            slope = np.polyfit(t[m], db[m], 1)[0]
            return RT60_MAX if slope >= -60 / RT60_MAX else -60.0 / slope

        r = fit(-5, -35) if db.min() < -36 else fit(-5, -25) if db.min() < -26 else fit(0, max(db.min() + 1, -25))
        if r is None:  # decay faster than one histogram bin
            r = dt
        rt[b] = min(r, RT60_MAX)
        e10 = fit(0.0, -10.0)
        edt[b] = min(e10 if e10 is not None else rt[b], RT60_MAX)
    return rt, edt


ROOM_MARGIN = 0.5  # m: a hit farther than this outside the probe's room's footprint has left the room


def outside_footprint(footprint: np.ndarray, xy: np.ndarray, margin: float = ROOM_MARGIN) -> np.ndarray:
    """(n,) bool: points (n, 2) outside the polygon by more than ``margin`` (walls stand on its outline)."""
    from sonicverse_core.scene.model import points_in_polygon

    out = ~points_in_polygon(xy, footprint)
    if out.any():
        p = xy[out]
        a, b = footprint, np.roll(footprint, -1, axis=0)
        ab = b - a
        t = np.clip(np.einsum("nkj,kj->nk", p[:, None] - a[None], ab) / np.maximum(np.sum(ab * ab, 1), 1e-12), 0, 1)
        d = np.min(np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=2), axis=1)
        out[np.flatnonzero(out)] = d > margin
    return out


def trace_decay(caster, position: np.ndarray, config: BakeConfig, room=None) -> tuple[np.ndarray, float]:
    """Ensemble energy in flight (9, T) on a grid of ``hist_dt`` and the fraction of rays that hit a surface.
    ``room`` (a :class:`Room`): the probe's own room; a ray whose next surface lies outside it has left through an
    opening and is lost to this room (its energy belongs to the neighbour, which the coupling accounts for)."""
    rng = np.random.default_rng(config.seed)
    alpha, scat, _ = material_arrays()
    scat = np.maximum(scat, config.min_scattering)
    nb = int(np.ceil(config.max_time / config.hist_dt)) + 1
    acc = np.zeros((len(BANDS), nb + 1))
    n = config.rays
    o = np.tile(position, (n, 1)).astype(np.float64)
    d = _uniform_dirs(rng, n)
    e = np.full((n, len(BANDS)), 1.0 / n)
    t = np.zeros(n)
    alive = np.arange(n)
    enclosed = None
    for _ in range(config.max_bounces):
        if len(alive) == 0:
            break
        h = caster.first_hit(o, d, include_dynamic=False)
        hit = h.hit
        if enclosed is None:
            enclosed = float(np.mean(hit))
        seg = np.where(hit, h.distance, (config.max_time - t) * SPEED_OF_SOUND)
        t1 = t + seg / SPEED_OF_SOUND
        # energy in flight on [t, t1): +e at the start bin, -e at the end bin (air loss applied per segment mid)
        e_mid = e * np.exp(-AIR_ABSORPTION[None] * seg[:, None] * 0.5)
        i0 = np.minimum((t / config.hist_dt).astype(int), nb)
        i1 = np.minimum((t1 / config.hist_dt).astype(int), nb)
        nbands = len(BANDS)
        off = (np.arange(nbands) * (nb + 1))[None, :]
        idx = np.concatenate([(i0[:, None] + off).ravel(), (i1[:, None] + off).ravel()])
        w = np.concatenate([e_mid.ravel(), -e_mid.ravel()])
        acc += np.bincount(idx, w, minlength=nbands * (nb + 1)).reshape(nbands, nb + 1)
        e_next = e * np.exp(-AIR_ABSORPTION[None] * seg[:, None])
        keep = hit & (t1 < config.max_time)
        e = e_next
        if room is not None and keep.any():
            ki = np.flatnonzero(keep)
            at = o[ki, :2] + d[ki, :2] * h.distance[ki, None]
            keep[ki[outside_footprint(room.footprint, at)]] = False
        mat = h.material[keep]
        e = e[keep] * (1.0 - alpha[mat])
        nrm = h.normal[keep]
        dk = d[keep]
        nrm = np.where((np.einsum("ij,ij->i", nrm, dk) > 0)[:, None], -nrm, nrm)
        spec = dk - 2 * np.einsum("ij,ij->i", dk, nrm)[:, None] * nrm
        if config.scattering == "vector":
            s_ = scat[mat][:, None]
            newd = s_ * _lambert(rng, nrm) + (1.0 - s_) * spec
            newd /= np.maximum(np.linalg.norm(newd, axis=1, keepdims=True), 1e-12)
        else:
            diffuse = rng.random(len(dk)) < scat[mat]
            newd = spec
            if np.any(diffuse):
                newd[diffuse] = _lambert(rng, nrm[diffuse])
        o = o[keep] + dk * h.distance[keep, None] + nrm * 1e-4
        d, t = newd, t1[keep]
        alive_e = e.max(1) > 1e-7 / n
        o, d, e, t = o[alive_e], d[alive_e], e[alive_e], t[alive_e]
        alive = np.arange(len(o))
    energy = np.cumsum(acc, axis=1)[:, :nb]
    return np.maximum(energy, 0.0), enclosed or 0.0


def proxy_box(caster, position: np.ndarray, far: float = 50.0, cone_deg: float = 20.0, per_axis: int = 37):
    """The room as a box around ``position``: along each of +-x, +-y, +-z, rays in a cone of ``cone_deg`` give the
    median distance to the nearest surface projected on the axis (so a door or window in the way does not push
    the wall away) and the most common material hit (Transparent where most rays escape)."""
    axes = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float)
    # a fixed spiral of directions in the cone around +z, rotated onto each axis
    k = np.arange(per_axis) + 0.5
    cos_t = 1 - (1 - np.cos(np.radians(cone_deg))) * k / per_axis
    phi = np.pi * (1 + 5 ** 0.5) * k
    sin_t = np.sqrt(1 - cos_t ** 2)
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], 1)
    dirs, owner = [], []
    for i, a in enumerate(axes):
        ref = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(a, ref)
        u /= np.linalg.norm(u)
        v = np.cross(a, u)
        dirs.append(local[:, :1] * u + local[:, 1:2] * v + local[:, 2:] * a)
        owner.append(np.full(per_axis, i))
    dirs, owner = np.concatenate(dirs), np.concatenate(owner)
    h = caster.first_hit(np.tile(position, (len(dirs), 1)), dirs, far, include_dynamic=False)
    proj = np.where(h.hit, h.distance * np.einsum("ij,ij->i", dirs, axes[owner]), far)
    dist, mats = np.empty(6), []
    for i in range(6):
        sel = owner == i
        dist[i] = float(np.median(proj[sel]))
        m = h.material[sel & h.hit]
        if len(m) < per_axis / 2:
            mats.append("Transparent")
        else:
            mats.append(MATERIAL_NAMES[int(np.bincount(m).argmax())])
    lo = position - np.array([dist[0], dist[2], dist[4]])
    hi = position + np.array([dist[1], dist[3], dist[5]])
    return lo, hi, tuple(mats)


def bake_probe(caster, position, config: BakeConfig = BakeConfig(), room=None) -> Probe:
    """``room``: the probe's own room (its decay then leaves out what escapes through openings: see
    :func:`trace_decay`); None: the whole connected space."""
    position = np.asarray(position, np.float64)
    if position.shape != (3,) or not np.all(np.isfinite(position)):
        raise ConfigError("a probe position must be 3 finite numbers")
    energy, enclosed = trace_decay(caster, position, config, room)
    rt, edt = decay_times(energy, config.hist_dt)
    lo, hi, mats = proxy_box(caster, position)
    return Probe(position, rt, edt, lo, hi, mats, enclosed, None if room is None else room.name)


def _cache_key(scene, positions: np.ndarray, config: BakeConfig, rooms: list) -> str:
    h = hashlib.sha256()
    h.update(scene.static_hash().encode())
    h.update(np.round(np.asarray(positions, np.float64), 4).tobytes())
    cfg = asdict(config)
    if not cfg["min_scattering"]:  # the default: the keys of bakes made before the field
        del cfg["min_scattering"]
    h.update(json.dumps(cfg, sort_keys=True).encode())
    for r in rooms:
        h.update(b"-" if r is None else np.round(np.asarray(r.footprint, np.float64), 4).tobytes())
    h.update(b"probes-v7")
    return h.hexdigest()[:24]


def bake(scene, positions, config: BakeConfig = BakeConfig(), caster=None, cache: bool = True,
         progress: bool = False) -> list[Probe]:
    """Bake probes at ``positions`` (k, 3), through the on-disk cache (``config.per_room``: each probe in a room
    bakes that room's own decay)."""
    from sonicverse_core.geometry.raycast import SceneRayCaster

    positions = np.atleast_2d(np.asarray(positions, np.float64))
    rooms = [scene.room_at(p[:2]) if config.per_room and scene.rooms else None for p in positions]
    path = None
    if cache:
        from assets_manifest import cache_dir

        path = cache_dir() / "bakes" / f"{_cache_key(scene, positions, config, rooms)}.json"
        if path.is_file():
            try:
                cached = json.loads(path.read_text())
                if not isinstance(cached, list) or len(cached) != len(positions):
                    raise ValueError(f"{type(cached).__name__} of {len(cached)} probes, expected {len(positions)}")
                return [_probe_from_json(p) for p in cached]
            except (ValueError, KeyError, TypeError) as exc:  # corrupt or foreign: baked again below
                import logging

                logging.getLogger(__name__).warning("bake cache %s is corrupt (%s): baked again", path, exc)
                path.unlink(missing_ok=True)
    caster = caster or SceneRayCaster(scene)
    from sonicverse_core.progress import progress as bar

    # as the cache will give them back: a scene sounds the same whether its bake was just made or read from disk
    # (a sampled policy's episode diverged on the fifth decimal of a decay time)
    probes = [bake_probe(caster, p, config, r).stored()
              for p, r in zip(bar(positions, len(positions), "baking probes", progress), rooms)]
    if path is not None:
        from sonicverse_core.storage import write_text_atomic

        write_text_atomic(path, json.dumps([p.to_json() for p in probes]))
    return probes


def _probe_from_json(d: dict) -> Probe:
    """A probe from its JSON form, checked: shapes, finite values, positive decay times, a box of positive size,
    known materials (ValueError otherwise)."""
    from sonicverse_core.scene.materials import MATERIAL_NAMES as known

    arr = {k: np.asarray(d[k], np.float64) for k in ("position", "rt60", "edt", "box_lo", "box_hi")}
    shapes = {"position": (3,), "rt60": (9,), "edt": (9,), "box_lo": (3,), "box_hi": (3,)}
    for k, shape in shapes.items():
        if arr[k].shape != shape or not np.isfinite(arr[k]).all():
            raise ValueError(f"probe '{k}' is not {shape} finite numbers")
    mats = tuple(d["box_materials"])
    enclosed = float(d["enclosed"])
    room = d.get("room")
    if room is not None and not isinstance(room, str):
        raise ValueError("probe 'room' must be a room's name or null")
    if np.any(arr["rt60"] <= 0) or np.any(arr["edt"] < 0) or np.any(arr["box_hi"] <= arr["box_lo"]) \
            or len(mats) != 6 or any(m not in known for m in mats) or not 0 <= enclosed <= 1:
        raise ValueError("probe values out of range (decay times, box, materials or enclosed fraction)")
    return Probe(arr["position"], arr["rt60"], arr["edt"], arr["box_lo"], arr["box_hi"], mats, enclosed, room)


PLACEMENT_CELLS = 1_000_000  # cells of the probe placement's floor grid where the navigation grid's would not fit


def default_probe_positions(scene, n: int | None = None, height: float = 1.5, rng=None) -> np.ndarray:
    """One probe per room at the free point of that room nearest its centre (a cell of the robot's navigable
    floor, else of the free floor, else, in a room lower than the robot, where the floor has a ceiling over it:
    :func:`_under_a_low_ceiling`; a room with none of these gets none), or ``n`` spread over the navigable floor.
    Each stands at ``height`` above the floor, lowered under a low ceiling (at most 0.3 m below it, at least half
    way up): never inside solid geometry, never outside the enclosure. (k, 3).

    The floor is found on the robot's navigation grid (5 cm cells), or, for a floor plan too large for that grid
    (over about 200 m x 200 m), on cells coarse enough for a million (up to 0.5 m; a room narrower than a metre
    or so then gets no probe of its own): a probe's place needs no finer floor."""
    from sonicverse_core.geometry.navgrid import MAX_CELL, MAX_CELLS, NavConfig, NavGrid, coarsest_cell

    cfg = NavConfig()
    if coarsest_cell(scene, MAX_CELLS) > cfg.cell:
        cfg = NavConfig(cell=min(MAX_CELL, max(cfg.cell, coarsest_cell(scene, PLACEMENT_CELLS))))
    grid = NavGrid(scene, cfg)
    if n is None:
        free = [grid.center_of(np.argwhere(mask)) for mask in (grid.labels == grid.main_label, grid.floor)]
        pts = []
        for r in scene.rooms:
            for xy in free:  # the robot's navigable floor first, else any free floor of the room
                xy = xy[r.contains(xy)] if len(xy) else xy
                if len(xy):
                    pts.append(xy[np.argmin(np.linalg.norm(xy - r.footprint.mean(0), axis=1))])
                    break
            else:  # no floor the robot's grid sees: a room lower than the robot
                low = _under_a_low_ceiling(grid, r)
                if low is not None:
                    pts.append(low)
        xy = np.array(pts).reshape(-1, 2)
    else:
        xy = grid.sample(rng or np.random.default_rng(0), n)
    return np.c_[xy, _ear_heights(grid, xy, height)]


def _under_a_low_ceiling(grid, room, candidates: int = 256):
    """The point (2,) of ``room``'s footprint nearest its centre, on the grid's cells, where the floor is free under a
    ceiling: straight down from 5 cm above the floor level an upward-facing surface within the grid's step of it,
    straight up a downward-facing one (static structure only). The robot's grid finds no floor in a room lower
    than the robot (its floor rays start at the robot's height, above that ceiling), so such a room had no probe
    and no reverb. None where no cell qualifies (a room that is solid through)."""
    xy = grid.center_of(np.argwhere(np.ones(grid.shape, bool)))
    xy = xy[room.contains(xy)]
    if len(xy) == 0:
        return None
    xy = xy[np.argsort(np.linalg.norm(xy - room.footprint.mean(0), axis=1))[:candidates]]
    z0 = grid.z_floor + 0.05
    o = np.c_[xy, np.full(len(xy), z0)]
    down = grid.caster.first_hit(o, np.tile([0.0, 0.0, -1.0], (len(xy), 1)), 1.0, include_dynamic=False)
    up = grid.caster.first_hit(o, np.tile([0.0, 0.0, 1.0], (len(xy), 1)), 100.0, include_dynamic=False)
    ok = down.hit & (down.normal[:, 2] > 0.7) & (down.distance <= 0.05 + grid.config.max_step) & \
        up.hit & (up.normal[:, 2] < -0.7) & (up.distance > 0.05)
    return xy[np.argmax(ok)] if ok.any() else None


def _ear_heights(grid, xy: np.ndarray, height: float) -> np.ndarray:
    """z of probes at xy: ``height`` above the floor, or lower under a low ceiling (rays cast up, static only)."""
    if len(xy) == 0:
        return np.zeros(0)
    z0 = grid.z_floor + 0.05
    h = grid.caster.first_hit(np.c_[xy, np.full(len(xy), z0)], np.tile([0.0, 0.0, 1.0], (len(xy), 1)), 100.0,
                              include_dynamic=False)
    room_h = np.where(h.hit, z0 + h.distance - grid.z_floor, np.inf)
    return grid.z_floor + np.minimum(height, np.maximum(room_h - 0.3, 0.5 * room_h))


def eyring_rt60(dims, alpha_surfaces: dict, air: bool = True) -> np.ndarray:
    """Eyring RT60 (9,) of a shoebox: 0.161 V / (-S ln(1 - mean alpha) + 4 m V)."""
    from sonicverse_core.scene.materials import get_material

    L, W, H = dims
    areas = {"floor": L * W, "ceiling": L * W, "x0": W * H, "x1": W * H, "y0": L * H, "y1": L * H}
    S = sum(areas.values())
    V = L * W * H
    mean_alpha = sum(areas[k] * np.array(get_material(alpha_surfaces[k]).absorption) for k in areas) / S
    m = AIR_ABSORPTION if air else 0.0
    with np.errstate(divide="ignore"):
        return 0.161 * V / (-S * np.log(np.maximum(1 - mean_alpha, 1e-12)) + 4 * m * V)




def reverb_free(scene) -> str | None:
    """Why this scene needs no reverb at all (no probes, no bake, no early reflections, no late reverb), or None:
    every static surface absorbs everything in every band (an anechoic room)."""
    from sonicverse_core.scene.materials import MATERIAL_NAMES, get_material

    mats = {MATERIAL_NAMES[int(i)] for i in np.unique(scene.static_mesh().face_material)}
    if all(min(get_material(m).absorption) >= 0.999 for m in mats):
        return f"every surface absorbs everything ({', '.join(sorted(mats))})"
    return None


def scene_probes(scene, config: BakeConfig = BakeConfig(), positions=None, progress: bool = False,
                 caster=None) -> list[Probe] | None:
    """The one recipe that gives a scene its reverb probes: one per room at its navigable point nearest the centre
    (or ``positions``), baked through the cache; None when the scene needs none (:func:`reverb_free`, or an open
    scene: no probe position is enclosed). A renderer given None builds no early reflections and no late reverb,
    and its ``subsystems`` say so."""
    if reverb_free(scene) is not None:
        return None
    from sonicverse_core.geometry.raycast import SceneRayCaster

    caster = caster or SceneRayCaster(scene)  # one for the enclosure check and the bake
    pos = default_probe_positions(scene) if positions is None else np.atleast_2d(np.asarray(positions, float))
    if len(pos) == 0 or not np.any(enclosed_fraction(scene, pos, caster=caster) > 0.5):
        return None
    return bake(scene, pos, config, caster=caster, progress=progress)


def enclosed_fraction(scene, positions, rays: int = 128, caster=None) -> np.ndarray:
    """Fraction of rays from each position that hit the static structure: near 0 in an open or anechoic scene,
    which needs no probes and no bake."""
    from sonicverse_core.geometry.raycast import SceneRayCaster

    caster = caster or SceneRayCaster(scene)
    d = _uniform_dirs(np.random.default_rng(0), rays)
    out = []
    for p in np.atleast_2d(positions):
        h = caster.first_hit(np.tile(p, (rays, 1)), d, 1000.0, include_dynamic=False)
        out.append(float(np.mean(h.hit)))
    return np.array(out)
