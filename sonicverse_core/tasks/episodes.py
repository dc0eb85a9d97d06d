"""Navigation episodes as in the paper: a home, a start pose, a target category and object, eight positions sampled
within 1 m of the object plus the navigable position nearest to it, less those from which a wall hides the object
(success at any of the rest within 0.36 m),
a sound of the target's category that plays for a sampled duration and then stops, and a start-goal geodesic
distance of 1-10 m. Episodes whose goal is unreachable are never generated: every terminal position and the start
lie in one connected component of the robot's collision map, and the start's geodesic distance is finite.

Homes: built-in apartments, split by seed (train / val / test never share a home); by default the first
:data:`DEFAULT_HOMES` seeds of each split are used. Sounds: heard (variants 0-2) or unheard (variant 3).
"""
from __future__ import annotations

import json
import weakref
from dataclasses import asdict, dataclass, field

import numpy as np

from sonicverse_core.errors import ConfigError

SUCCESS_RADIUS = 0.36  # m: the TurtleBot's width
GOAL_RADIUS = 1.0  # m around the target object
DEFAULT_HOMES = {"train": 16, "val": 4, "test": 8}
SOUND_SECONDS = (4.0, 20.0)


def _tuples(v):
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


class JsonRecord:
    """``to_json`` / ``from_json`` for frozen episode dataclasses (JSON lists come back as tuples)."""

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str):
        return cls(**{k: _tuples(v) for k, v in json.loads(text).items()})


@dataclass(frozen=True)
class Episode(JsonRecord):
    episode_id: str
    scene: str  # scene spec
    split: str
    start: tuple  # (x, y, yaw_deg)
    category: str
    object_name: str
    goals: tuple  # up to nine (x, y), the object in sight from each
    sound: str  # 'category/variant'
    sound_seconds: float
    source_gain: float = 1.0
    geodesic: float = 0.0  # m from start to the nearest goal
    extra: dict = field(default_factory=dict)


def homes(split: str, n: int | None = None) -> list[str]:
    from sonicverse_core.scene.apartment import seeds_for

    seeds = seeds_for(split)
    n = DEFAULT_HOMES.get(split, 4) if n is None else int(n)
    if not (1 <= n <= len(seeds)):
        raise ConfigError(f"number of homes for split '{split}' must be 1..{len(seeds)}, got {n}")
    return [f"builtin:apartment?seed={s}" for s in seeds[:n]]


_structure_casters = weakref.WeakKeyDictionary()  # scene -> its structure's RayCaster


def structure_caster(scene):
    """A :class:`~sonicverse_core.geometry.raycast.RayCaster` over ``scene.static_mesh()``, built once per scene
    (a home's episodes share it)."""
    caster = _structure_casters.get(scene)
    if caster is None:
        from sonicverse_core.geometry.raycast import RayCaster

        caster = _structure_casters[scene] = RayCaster(scene.static_mesh())
    return caster


def in_sight(scene, obj, pts: np.ndarray) -> np.ndarray:
    """(n,) bool: no part of the scene's structure (walls, windows) lies between each (x, y) of ``pts`` and the
    nearest point of ``obj``'s footprint, at the height of the object's middle (kept within 0.3-1.2 m: a picture on
    the wall is seen from below it)."""
    caster = structure_caster(scene)
    lo, hi = obj.world_bounds()
    z = float(np.clip((lo[2] + hi[2]) / 2, 0.3, 1.2))
    pts = np.asarray(pts, float)
    a = np.c_[pts, np.full(len(pts), z)]
    b = np.c_[np.clip(pts, lo[:2], hi[:2]), np.full(len(pts), z)]
    seg = b - a
    length = np.linalg.norm(seg, axis=1)
    reach = np.maximum(length - 0.02, 0.0)  # short of the object's face, which may touch a wall
    ok = reach > 0
    out = np.ones(len(pts), bool)
    if ok.any():
        h = caster.first_hit(a[ok], seg[ok] / length[ok, None], reach[ok])
        out[ok] = ~(h.distance < reach[ok])
    return out


def goal_positions(world, obj, rng: np.random.Generator, k: int = 8) -> np.ndarray | None:
    """Up to nine (x, y) terminal positions for object ``obj`` (the navigable cell nearest to it first, then ``k``
    sampled within GOAL_RADIUS of its footprint), all in one component, less those from which a wall hides the
    object (:func:`in_sight`: a position within 1 m of a shelf may be in the next room, behind the wall the shelf
    stands against); None if there are not enough, or none in sight. The draws do not depend on which are hidden,
    so an episode is the same as before that check but for its hidden terminal positions."""
    grid = world.grid
    lo, hi = obj.world_bounds()[:, :2]
    c = grid.config.cell
    rc0 = grid.cell_of(lo - GOAL_RADIUS - c)[0]
    rc1 = grid.cell_of(hi + GOAL_RADIUS + c)[0]
    r0, r1 = max(rc0[0], 0), min(rc1[0], grid.shape[0] - 1)
    c0, c1 = max(rc0[1], 0), min(rc1[1], grid.shape[1] - 1)
    if r1 < r0 or c1 < c0:
        return None
    sub = grid.labels[r0:r1 + 1, c0:c1 + 1] == grid.main_label
    rows, cols = np.nonzero(sub)
    if len(rows) < k + 1:
        return None
    from sonicverse_core.world.world import box_distance

    pts = grid.center_of(np.stack([rows + r0, cols + c0], 1))
    d = box_distance(lo, hi, pts)
    ok = d <= GOAL_RADIUS
    pts, d = pts[ok], d[ok]
    if len(pts) < k + 1:
        return None
    first = int(np.argmin(d))
    rest = np.delete(np.arange(len(pts)), first)
    pick = rng.choice(rest, size=k, replace=False)
    out = np.concatenate([pts[first:first + 1], pts[np.sort(pick)]])
    out = out[in_sight(world.scene, obj, out)]
    return out if len(out) else None


def sample_episode(world, scene_spec: str, split: str, sounds: str, rng: np.random.Generator,
                   episode_id: str, geodesic_range=(1.0, 10.0), sound_seconds=SOUND_SECONDS,
                   categories=None, tries: int = 200) -> Episode | None:
    """One episode in ``world`` (None when this home has no valid one)."""
    from assets_manifest.soundbank import CATEGORIES, HEARD, UNHEARD

    if sounds not in ("heard", "unheard"):
        raise ConfigError(f"sounds must be 'heard' or 'unheard', got '{sounds}'")
    cats = set(categories or CATEGORIES)
    objs = [o for o in world.scene.objects if o.category in cats]
    by_cat: dict[str, list] = {}
    for o in objs:
        by_cat.setdefault(o.category, []).append(o)
    names = sorted(by_cat)
    while names:
        cat = names[int(rng.integers(len(names)))]
        cands = by_cat[cat]
        obj = cands[int(rng.integers(len(cands)))]
        goals = goal_positions(world, obj, rng)
        ok = np.zeros(0, int)
        if goals is not None:
            field_ = world.grid.distance_field(goals)
            starts = world.grid.sample(rng, tries)
            geo = world.grid.geodesic_from_field(field_, starts)
            ok = np.flatnonzero((geo >= geodesic_range[0]) & (geo <= geodesic_range[1]) & np.isfinite(geo))
        if len(ok) == 0:  # no goals or no start at the right distance: never offer this object again
            cands.remove(obj)
            if not cands:
                names.remove(cat)
            continue
        i = int(ok[0])
        yaw = float(rng.uniform(-180.0, 180.0))
        variants = HEARD if sounds == "heard" else UNHEARD
        var = int(variants[int(rng.integers(len(variants)))])
        return Episode(episode_id=episode_id, scene=scene_spec, split=split,
                       start=(float(starts[i, 0]), float(starts[i, 1]), yaw), category=cat, object_name=obj.name,
                       goals=tuple((float(x), float(y)) for x, y in goals), sound=f"{cat}/{var}",
                       sound_seconds=float(rng.uniform(*sound_seconds)), geodesic=float(geo[i]))
    return None
