"""`sonicverse bench fidelity`: error against run time for sound between rooms.

A suite of rooms, each rendered by our renderer (mono output, an impulse) and by pyroomacoustics' hybrid simulator
(image sources to order 3 + stochastic ray tracing, the same 9-band absorption and scattering, its own air
absorption model; ours uses Resonance Audio's coefficients) in the same run, and, where theory has an answer,
against theory: Eyring's T and Barron's revised theory's G for the shoeboxes, the mass-law estimate
D = TL - 10 log10(S / A2) for the sealed rooms (pyroomacoustics has no transmission through walls).

Per case and octave band (250 Hz - 4 kHz): strength G (dB re the free field at 10 m; both use the 1/r law), T30,
EDT (s), C50 (dB) and DRR (dB, the first arrival's +-2.5 ms over the rest), ours vs the peer, and our run time
(bake and render) vs the peer's. Targets (issue 15): G within 3 dB, T30 within 20% (10% in the diffuse shoebox),
C50 within 3 dB, EDT within 25%; sealed: D within 3 dB of the estimate. Each case also gives where in time the two
responses part: ours over the peer's energy per band in windows after the direct sound (:func:`window_energies`).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from sonicverse_core.acoustics.config import RenderConfig as _RC

BANDS = (250, 500, 1000, 2000, 4000)
BUILDUP = _RC.tail_buildup  # the renderer's default: the bench's default model is the renderer's
BEAM = _RC.tail_beam
NEIGHBOURS = _RC.neighbour_tails
FS = 16_000
C = 343.0


def _band(h: np.ndarray, f0: float, fs: int) -> np.ndarray:
    from scipy.signal import butter, sosfilt

    sos = butter(4, [f0 / np.sqrt(2), min(f0 * np.sqrt(2), 0.99 * fs / 2)], btype="band", fs=fs, output="sos")
    return sosfilt(sos, h)


def _fit(db: np.ndarray, t: np.ndarray, hi: float, lo: float) -> float | None:
    m = (db <= hi) & (db >= lo)
    if np.count_nonzero(m) < 5:
        return None
    slope = np.polyfit(t[m], db[m], 1)[0]
    return -60.0 / slope if slope < 0 else None


def _responses(h) -> list:
    """A response or a list of them (realisations) as float arrays of one length (zero-padded)."""
    hs = [np.asarray(x, float) for x in h] if isinstance(h, (list, tuple)) else [np.asarray(h, float)]
    n = max(len(x) for x in hs)
    return [np.pad(x, (0, n - len(x))) for x in hs]


def _band_power(hs: list, f0: float, fs: int) -> np.ndarray:
    """The mean over responses ``hs`` of their squared octave-band signals at ``f0``: the ensemble's expected energy
    in time."""
    return np.mean([_band(y, f0, fs) ** 2 for y in hs], axis=0)


def room_parameters(h, fs: int = FS, t_dir: int | None = None) -> dict:
    """G, T30, EDT, C50, DRR per band of a mono impulse response (1/r law: a unit source gives 1/r). The decay
    curves and C50 / DRR start at ``t_dir`` (samples; the direct sound's time), by default where the response first
    comes within 20 dB of its peak (ISO 3382-1's onset, which behind a wall can be a late, loud arrival).

    ``h`` may also be a list of responses of the same room (realisations of a stochastic model: other noise, other
    rays): the parameters are then those of their mean squared band signals, the ensemble's expected energy
    decay, so that one realisation's chance (an octave at 250 Hz holds few degrees of freedom in 50 ms) does not
    decide a comparison."""
    hs = _responses(h)
    imp = np.zeros(fs)
    imp[0] = 1.0
    e0 = np.abs(hs[0])
    if t_dir is None:
        t_dir = int(np.argmax(e0 > 0.1 * e0.max()))  # the first arrival within 20 dB of the peak
    out = {k: [] for k in ("G", "T30", "EDT", "C50", "DRR")}
    for f0 in BANDS:
        x = _band_power(hs, f0, fs)
        ref = np.sum(_band(imp, f0, fs) ** 2) * 0.1 ** 2
        out["G"].append(10 * np.log10(np.sum(x) / ref))
        x = x[t_dir:]
        sch = np.cumsum(x[::-1])[::-1]
        db = 10 * np.log10(np.maximum(sch / sch[0], 1e-30))
        t = np.arange(len(x)) / fs
        out["T30"].append(_fit(db, t, -5, -35) or _fit(db, t, -5, -25))
        out["EDT"].append(_fit(db, t, 0, -10))
        k50, kd = int(0.05 * fs), int(0.0025 * fs)
        out["C50"].append(10 * np.log10(np.sum(x[:k50]) / max(np.sum(x[k50:]), 1e-30)))
        out["DRR"].append(10 * np.log10(np.sum(x[:kd]) / max(np.sum(x[kd:]), 1e-30)))
    return {k: [None if v is None else round(float(v), 3) for v in vals] for k, vals in out.items()}


WINDOWS_MS = (0, 20, 50, 100, 200, 400, 800, 1600)  # window_energies' edges after the direct sound


def window_energies(h, fs: int = FS, t_dir: int = 0) -> np.ndarray:
    """(5, 7) energy per octave band (``BANDS``) in the windows ``WINDOWS_MS`` after ``t_dir`` (samples) of a mono
    response or of the mean squared band signals of a list of them (as :func:`room_parameters`): where in time two
    responses part, which G, EDT and C50 sum over."""
    hs = _responses(h)
    edges = [t_dir + int(ms * fs / 1000) for ms in WINDOWS_MS]
    out = np.zeros((len(BANDS), len(edges) - 1))
    for b, f0 in enumerate(BANDS):
        x = _band_power(hs, f0, fs)
        out[b] = [x[a:z].sum() for a, z in zip(edges[:-1], edges[1:])]  # past the end: what there is
    return out


def _pra_material(name: str, min_scattering: float = 0.0):
    import pyroomacoustics as pra

    from sonicverse_core.scene.materials import BANDS as ALL, get_material

    m = get_material(name)
    return pra.Material(energy_absorption={"coeffs": list(m.absorption[1:8]), "center_freqs": list(ALL[1:8])},
                        scattering=max(m.scattering, min_scattering))


def _pra_floors(room, corners, H, floors, walls, floor, ceiling, lintels=None, leaves=None, min_scattering=0.0):
    """The extruded room's walls with its floor and ceiling replaced by one polygon per entry of ``floors``
    ((xy corners, floor material, ceiling material)), a box hung from the ceiling per entry of ``lintels``
    ((x0, x1, y0, y1, z0, material): its underside at z0 and its two faces across x, as over a doorway), and a box
    standing on the floor per entry of ``leaves`` ((x0, x1, y0, y1, z1, material): an open door's leaf, its four
    sides and its top at z1). A material's coefficients are those of an outline wall of that material, or its own
    resampled to the peer's bands."""
    import pyroomacoustics as pra

    names = (walls if isinstance(walls, list) else [walls] * len(corners)) + [floor, ceiling]
    known = {m: (w.absorption, w.scatter) for m, w in zip(names, room.walls)}

    def coeffs(name):
        if name not in known:
            m = _pra_material(name, min_scattering)
            m.resample(room.octave_bands)
            known[name] = (np.asarray(m.absorption_coeffs, float), np.asarray(m.scattering_coeffs, float))
        return known[name]

    def face(pts, outward, mat, name):  # outward: into the solid (pyroomacoustics' walls face away from the air)
        pts = np.asarray(pts, float)
        if np.dot(np.cross(pts[1] - pts[0], pts[2] - pts[1]), outward) < 0:
            pts = pts[::-1]
        a, sc = coeffs(mat)
        return pra.wall_factory(pts.T, a, sc, name)

    if floors:
        out = list(room.walls[:len(corners)])
        for xy, fmat, cmat in floors:
            xy = np.asarray(xy, float)
            for z, mat, up in ((0.0, fmat, False), (H, cmat, True)):
                out.append(face(np.c_[xy, np.full(len(xy), z)], (0, 0, 1 if up else -1), mat,
                                "ceiling" if up else "floor"))
    else:
        out = list(room.walls)
    for x0, x1, y0, y1, z0, mat in lintels or ():
        out.append(face([(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)], (0, 0, 1), mat, "lintel"))
        for x, sign in ((x0, 1), (x1, -1)):
            out.append(face([(x, y0, z0), (x, y1, z0), (x, y1, H), (x, y0, H)], (sign, 0, 0), mat, "lintel"))
    for x0, x1, y0, y1, z1, mat in leaves or ():
        out.append(face([(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], (0, 0, -1), mat, "leaf"))
        for x, sign in ((x0, 1), (x1, -1)):
            out.append(face([(x, y0, 0), (x, y1, 0), (x, y1, z1), (x, y0, z1)], (sign, 0, 0), mat, "leaf"))
        for y, sign in ((y0, 1), (y1, -1)):
            out.append(face([(x0, y, 0), (x1, y, 0), (x1, y, z1), (x0, y, z1)], (0, sign, 0), mat, "leaf"))
    return pra.Room(out, fs=room.fs, max_order=room.max_order, air_absorption=True, ray_tracing=True)


def _pra_room(corners, H, walls, floor, ceiling, floors=None, lintels=None, leaves=None, min_scattering=0.0):
    """The peer's room: the outline extruded to H with image sources to order 3 (ray tracing on), per-room floors
    and ceilings, the wall over a doorway and an open door's leaf where given (:func:`_pra_floors`); every
    material scattering at least ``min_scattering``."""
    import pyroomacoustics as pra

    ms = min_scattering
    mats = [_pra_material(m, ms) for m in walls] if isinstance(walls, list) else _pra_material(walls, ms)
    room = pra.Room.from_corners(np.array(corners, float).T, fs=FS, max_order=3, materials=mats,
                                 ray_tracing=True, air_absorption=True)
    room.extrude(H, materials={"floor": _pra_material(floor, ms), "ceiling": _pra_material(ceiling, ms)})
    if floors or lintels or leaves:  # rooms with floors and ceilings of their own; the wall over a doorway; a leaf
        room = _pra_floors(room, corners, H, floors, walls, floor, ceiling, lintels, leaves, ms)
    return room


def _pra_polygon(corners, H, walls, floor, ceiling, src, lis, rays, seed: int = 0, floors=None, lintels=None,
                 leaves=None, min_scattering: float = 0.0):
    import pyroomacoustics as pra

    pra.random.seed(seed)  # its ray tracing draws from NumPy's and C++'s generators: the same run, the same numbers
    room = _pra_room(corners, H, walls, floor, ceiling, floors, lintels, leaves, min_scattering)
    room.set_ray_tracing(n_rays=rays, receiver_radius=0.5)
    room.add_source(list(src))
    room.add_microphone(np.array(lis, float)[:, None])
    room.compute_rir()
    return np.asarray(room.rir[0][0], float)


def _ours(spec: str, src, lis, seconds: float, scattering: str = "stochastic",
          er_order: int = 1, per_room: bool = True, er_images: str = "room",
          realisation: int = 0, tail_edt: bool = True,
          tail_buildup: float = BUILDUP, neighbour_tails: int = NEIGHBOURS,
          reverb: str = "convolution", tail_beam: float = BEAM,
          min_scattering: float = 0.0) -> tuple[np.ndarray, float, float]:
    """Our mono impulse response; ``realisation`` > 0: another bake seed and another tail noise (0: the defaults);
    ``min_scattering``: ``BakeConfig.min_scattering``."""
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(spec)
    t0 = time.perf_counter()
    bake = BakeConfig(scattering=scattering, per_room=per_room, min_scattering=min_scattering)
    probes = scene_probes(scene, dataclasses.replace(bake, seed=bake.seed + realisation))
    r = AcousticRenderer(scene, RenderConfig(sample_rate=FS, output="mono", er_order=er_order,
                                             er_images=er_images, tail_seed=realisation, tail_edt=tail_edt,
                                             tail_buildup=tail_buildup, neighbour_tails=neighbour_tails,
                                             reverb=reverb, tail_beam=tail_beam),
                          probes=probes)
    t_bake = time.perf_counter() - t0
    x = np.zeros(int(seconds * FS), np.float32)
    x[0] = 1.0
    r.add_source(x, position=src, loop=False)
    r.add_listener(lis)
    t0 = time.perf_counter()
    out = r.render(seconds)[0]
    t_render = time.perf_counter() - t0
    return out.astype(float).sum(0) / np.sqrt(2), t_bake, t_render  # mono: each channel carries 1/sqrt(2)


SHOEBOXES = {
    "shoebox small absorbing": ((4.0, 3.0, 2.5), "WoodPanel", "ParquetOnConcrete", "AcousticCeilingTiles"),
    "shoebox medium diffuse": ((8.0, 6.0, 3.0), "PlasterRough", "ParquetOnConcrete", "PlasterRough"),
    "shoebox large absorbing ceiling": ((12.0, 9.0, 4.0), "BrickBare", "LinoleumOnConcrete", "AcousticCeilingTiles"),
}
L_ROOM = [(0, 0), (6, 0), (6, 3), (3, 3), (3, 6), (0, 6)]
TWO_ROOMS = [(0, 0), (3.95, 0), (3.95, 1.55), (4.05, 1.55), (4.05, 0), (8, 0), (8, 4), (4.05, 4), (4.05, 2.45),
             (3.95, 2.45), (3.95, 4), (0, 4)]  # the partition as a 0.1 m notch, cut through to the ceiling...
THREE_ROOMS = [(0, 0), (3.95, 0), (3.95, 1.55), (4.05, 1.55), (4.05, 0), (7.95, 0), (7.95, 1.55), (8.05, 1.55),
               (8.05, 0), (12, 0), (12, 4), (8.05, 4), (8.05, 2.45), (7.95, 2.45), (7.95, 4), (4.05, 4), (4.05, 2.45),
               (3.95, 2.45), (3.95, 4), (0, 4)]  # two partitions, two doorways


def _cases():
    from sonicverse_core.scene import reference as ref

    for name, (dims, walls, floor, ceiling) in SHOEBOXES.items():
        L, W, H = dims
        spec = f"shoebox:{L:g}x{W:g}x{H:g}?walls={walls}&floor={floor}&ceiling={ceiling}"
        src, lis = (0.3 * L, 0.35 * W, 1.2), (0.7 * L, 0.6 * W, 1.5)
        corners = [(0, 0), (L, 0), (L, W), (0, W)]
        yield name, spec, corners, H, (walls, floor, ceiling), src, lis, dims
    mats = (ref.WALLS, ref.FLOOR, ref.CEILING)
    # the partition's faces (walls 1-3 and 7-9 of the outline) are the partition's material, as in our scene
    # ... and the wall over the doorway (ours is 0.9 x 2.1 m): the partition's lintel
    lintel = [(3.95, 4.05, 1.55, 2.45, ref.DOOR_HEIGHT, ref.PARTITION)]
    # ... and the open door's leaf (session 20): ours swings into the east room along the south jamb, 4 cm thick,
    # and stands in the way of a straight line through the doorway's south edge (1 cm off the partition's face here)
    leaf = [(4.06, 4.0 + ref.DOOR_WIDTH, 1.53, 1.57, ref.DOOR_HEIGHT - 0.01, ref.DOOR)]
    two = ([ref.PARTITION if k in (1, 2, 3, 7, 8, 9) else ref.WALLS for k in range(len(TWO_ROOMS))], ref.FLOOR,
           ref.CEILING, None, lintel, leaf)
    # Sources at 1.2 m and listeners at 1.5 m, as in the shoeboxes, and never mirror images of each other across a
    # mid-plane of the room (z_s + z_l != H; in the L-room's corridor y_s + y_l != its width), as ISO 3382-1 asks of
    # measurement positions. Until session 25 both stood at 1.5 m (and in the corridor on its axis): the image
    # sources of opposite surfaces then arrive at the same instant, and the peer, which adds its images' pressures,
    # adds them in phase (+6 dB for four) where ours adds their energies; the L-room's C50 missed by 3.2-4.1 dB on
    # that alone (tests/test_paths.py).
    yield "L-room, line of sight", "builtin:l-room", L_ROOM, 3.0, mats, (5.0, 1.2, 1.2), (1.5, 1.5, 1.5), None
    yield "L-room, round the corner", "builtin:l-room", L_ROOM, 3.0, mats, (5.0, 1.2, 1.2), (1.5, 5.0, 1.5), None
    yield ("two rooms, open door, line of sight", "builtin:two-rooms?door=open", TWO_ROOMS, 3.0, two,
           (2.0, 2.6, 1.2), (6.0, 1.7, 1.5), None)
    yield ("two rooms, open door, no line of sight", "builtin:two-rooms?door=open", TWO_ROOMS, 3.0, two,
           (2.0, 2.6, 1.2), (6.0, 0.6, 1.5), None)
    # a dead room (every surface absorbing) beside a live one: coupled decay at its starkest
    dead = "AcousticCeilingTiles"
    walls = [dead if k in (0, 10, 11) else ref.PARTITION if k in (1, 2, 3, 7, 8, 9) else ref.WALLS
             for k in range(len(TWO_ROOMS))]
    floors = [([(0, 0), (3.95, 0), (3.95, 4), (0, 4)], dead, dead),
              ([(3.95, 1.55), (4.05, 1.55), (4.05, 2.45), (3.95, 2.45)], ref.FLOOR, ref.CEILING),
              ([(4.05, 0), (8, 0), (8, 4), (4.05, 4)], ref.FLOOR, ref.CEILING)]
    spec = f"builtin:two-rooms?door=open&west={dead}"
    yield ("dead room beside a live one, both in the dead", spec, TWO_ROOMS, 3.0,
           (walls, ref.FLOOR, ref.CEILING, floors, lintel, leaf), (1.2, 1.2, 1.2), (2.8, 3.0, 1.5), None)
    yield ("dead room beside a live one, source in the live", spec, TWO_ROOMS, 3.0,
           (walls, ref.FLOOR, ref.CEILING, floors, lintel, leaf), (6.0, 1.0, 1.2), (1.0, 0.6, 1.5), None)
    # the same source heard in its own room (session 63): the live room's decay where it rings, against which the
    # dead room's listener above hears what comes through the doorway
    yield ("dead room beside a live one, both in the live", spec, TWO_ROOMS, 3.0,
           (walls, ref.FLOOR, ref.CEILING, floors, lintel, leaf), (6.0, 1.0, 1.2), (7.0, 3.2, 1.5), None)
    # three rooms in a row (session 36): a live west room, a dead hall, an east room less live than the west; the
    # east room's decay, heard in the hall, is not the slowest mode's (the west's): more than one neighbour apart
    live = "WoodPanel"
    room_of = {0: "w", 4: "m", 8: "e", 9: "e", 10: "e", 14: "m", 18: "w", 19: "w"}
    mat = {"w": ref.WALLS, "m": dead, "e": live}
    walls = [mat[room_of[k]] if k in room_of else ref.PARTITION for k in range(len(THREE_ROOMS))]
    strip = lambda x: ([(x - 0.05, 1.55), (x + 0.05, 1.55), (x + 0.05, 2.45), (x - 0.05, 2.45)],  # noqa: E731
                       ref.FLOOR, ref.CEILING)
    floors = [([(0, 0), (3.95, 0), (3.95, 4), (0, 4)], ref.FLOOR, ref.CEILING), strip(4.0),
              ([(4.05, 0), (7.95, 0), (7.95, 4), (4.05, 4)], dead, dead), strip(8.0),
              ([(8.05, 0), (12, 0), (12, 4), (8.05, 4)], live, live)]
    lintels = [(x - 0.05, x + 0.05, 1.55, 2.45, ref.DOOR_HEIGHT, ref.PARTITION) for x in (4.0, 8.0)]
    leaves = [(x + 0.06, x + ref.DOOR_WIDTH, 1.53, 1.57, ref.DOOR_HEIGHT - 0.01, ref.DOOR) for x in (4.0, 8.0)]
    yield ("dead hall between two live rooms, source in the east", f"builtin:three-rooms?door=open&middle={dead}"
           f"&east={live}", THREE_ROOMS, 3.0, (walls, ref.FLOOR, ref.CEILING, floors, lintels, leaves),
           (10.0, 1.2, 1.2), (6.0, 3.0, 1.5), None)


PRA_DELAY = 40  # samples: pyroomacoustics centres each arrival in an 81-tap fractional-delay filter


def _onset(spec: str, src, lis) -> int:
    """The direct sound's time (samples at FS) from source to listener along the shortest open path: the straight
    line in sight, else the path graph's path (its 2-D length with the height difference). Both responses' decay
    curves, C50 and DRR start there, as ISO 3382-1 starts them at the direct sound; behind a wall the standard's
    onset (within 20 dB of the peak) can be a loud arrival 10 ms later in one response and the weak first one in
    the other."""
    from sonicverse_core.acoustics.paths import path_graph
    from sonicverse_core.scene.spec import load_scene

    src, lis = np.asarray(src, float), np.asarray(lis, float)
    g = path_graph(load_scene(spec))
    L = float(np.linalg.norm(lis - src))
    if not g.line_of_sight(src, lis):
        res = g.path(src[:2], lis[:2])
        if res is not None:
            L = float(np.hypot(res.length, lis[2] - src[2]))
    return int(round(L / C * FS))


def _theory_shoebox(dims, walls, floor, ceiling, src, lis) -> dict:
    from sonicverse_core.acoustics.probes import eyring_rt60

    T = eyring_rt60(dims, {"floor": floor, "ceiling": ceiling, "x0": walls, "x1": walls, "y0": walls,
                           "y1": walls}, air=True)[[3, 4, 5, 6, 7]]
    V = float(np.prod(dims))
    r = float(np.linalg.norm(np.subtract(src, lis)))
    G = 10 * np.log10(100 / r ** 2 + 31200 * T / V * np.exp(-0.04 * r / T))
    return {"G": np.round(G, 3).tolist(), "T30": np.round(T, 3).tolist()}


TARGETS = {"G": ("abs_db", 3.0), "T30": ("rel", 0.20), "C50": ("abs_db", 3.0), "EDT": ("rel", 0.25)}


def _errors(ours: dict, peer: dict, diffuse: bool) -> dict:
    out = {}
    for k, (kind, tol) in TARGETS.items():
        tol = 0.10 if diffuse and k == "T30" else tol
        errs = []
        for a, b in zip(ours[k], peer[k]):
            if a is None or b is None:
                errs.append(None)
            else:
                errs.append(round(a - b, 3) if kind == "abs_db" else round(a / b - 1, 3))
        ok = all(e is not None and abs(e) <= tol for e in errs)
        out[k] = {"error": errs, "tolerance": tol, "met": ok}
    return out


def _sealed(scattering: str = "stochastic", per_room: bool = True, tail_edt: bool = True,
            tail_buildup: float = BUILDUP, reverb: str = "convolution", tail_beam: float = BEAM) -> dict:
    """Sealed rooms: our level difference between the rooms per band vs D = TL - 10 log10(S / A2)."""
    from sonicverse_core.acoustics.coupling import RoomCoupling
    from sonicverse_core.acoustics.paths import path_graph
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.scene.materials import get_material
    from sonicverse_core.scene.spec import load_scene

    spec = "builtin:two-rooms?door=sealed"
    src = (2.0, 2.0, 1.5)
    G1, G2 = [], []
    t = 0.0
    for lis in ((1.0, 1.0, 1.5), (3.0, 3.2, 1.5)):
        h, tb, tr = _ours(spec, src, lis, 3.0, scattering, per_room=per_room, tail_edt=tail_edt,
                          tail_buildup=tail_buildup, reverb=reverb, tail_beam=tail_beam)
        G1.append(room_parameters(h)["G"])
        t += tr
    for lis in ((5.5, 1.0, 1.5), (7.0, 3.2, 1.5)):
        h, tb, tr = _ours(spec, src, lis, 3.0, scattering, per_room=per_room, tail_edt=tail_edt,
                          tail_buildup=tail_buildup, reverb=reverb, tail_beam=tail_beam)
        G2.append(room_parameters(h)["G"])
        t += tr
    mean = lambda G: 10 * np.log10(np.mean(10 ** (np.array(G) / 10), axis=0))  # noqa: E731
    D = mean(G1) - mean(G2)
    scene = load_scene(spec)
    c = RoomCoupling(scene, path_graph(scene), scene_probes(scene, BakeConfig(scattering=scattering,
                                                                                     per_room=per_room)))
    tl = np.array(get_material("Sheetrock").transmission_loss_db)[[3, 4, 5, 6, 7]]
    est = tl - 10 * np.log10(4.0 * 3.0 / c.A[1][[3, 4, 5, 6, 7]])
    err = D - est
    return {"case": "two rooms, sealed (vs the mass-law estimate)", "bands_hz": list(BANDS),
            "D_ours_db": np.round(D, 2).tolist(), "D_estimate_db": np.round(est, 2).tolist(),
            "error_db": np.round(err, 2).tolist(), "met": bool(np.all(np.abs(err) <= 3.0)),
            "our_render_s": round(t, 2)}


def bench_fidelity(rays: int = 20_000, plot: str | None = None, quick: bool = False, seed: int = 0,
                   scattering: str = "stochastic", er_order: int = 1, per_room: bool = True,
                   er_images: str = "room", realisations: int = 1, tail_edt: bool = True,
                   tail_buildup: float = BUILDUP, neighbour_tails: int = NEIGHBOURS, case: str | None = None,
                   reverb: str = "convolution", tail_beam: float = BEAM, min_scattering: float = 0.0) -> dict:
    """``scattering``: our bake's scattering model (``BakeConfig.scattering``; the peer's is "vector");
    ``er_order``, ``er_images``: our image sources' order and geometry (``RenderConfig``); ``per_room``: probes baked per room, the
    rooms' decays coupled (``BakeConfig.per_room``); ``tail_edt``: our tails fall first at the bake's EDT
    (``RenderConfig.tail_edt``); ``tail_buildup``: the late part of a source in another room builds up with this
    time constant (s; ``RenderConfig.tail_buildup``), its share ``tail_beam`` (``RenderConfig.tail_beam``; the rest
    at the coupled rooms' own rate); ``neighbour_tails``: coupled rooms heard apart besides the
    slowest mode's (``RenderConfig.neighbour_tails``); ``reverb``: our late reverb, the convolution or the cheaper
    FDN (``RenderConfig.reverb``); ``min_scattering``: every material scatters at least this much in both models
    (``BakeConfig.min_scattering``; the peer's materials likewise; no sealed rooms): at 1 every bounce is
    Lambertian in both, one reflection law, so what is left is the rest of the two models (the scattering models
    part most where s is small: ``probes``' docstring); ``case``: only the cases whose name contains it (and no
    sealed rooms unless it names them). ``realisations`` N > 1: both models run N times (the peer with
    seeds ``seed`` .. ``seed + N - 1``, ours with N bake seeds and tail noises) and each case's parameters are
    those of the mean squared band signals (:func:`room_parameters`): the models' expected responses compared,
    not one draw of each."""
    if not (1 <= realisations <= 64):
        from sonicverse_core.errors import ConfigError

        raise ConfigError(f"realisations must be within 1..64, got {realisations}")
    from sonicverse_core.acoustics.probes import BakeConfig
    from sonicverse_core.acoustics.renderer import RenderConfig
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.progress import progress

    BakeConfig(scattering=scattering, min_scattering=min_scattering)  # checked before anything runs
    RenderConfig(er_order=er_order, er_images=er_images, tail_buildup=tail_buildup, tail_beam=tail_beam,
                 neighbour_tails=neighbour_tails, reverb=reverb)
    seconds = 3.0
    todo = list(_cases())
    if quick:
        todo = todo[1:2] + todo[4:5] + todo[6:7]
    if case is not None:
        todo = [c for c in todo if case.lower() in c[0].lower()]
        if not todo and "sealed" not in case.lower():
            raise ConfigError(f"no fidelity case matches '{case}'; the cases: {', '.join(c[0] for c in _cases())}")
        if not todo and min_scattering:
            raise ConfigError("the sealed rooms are compared with the mass law, not the peer: no --min-scattering")
    cases = []
    for name, spec, corners, H, mats, src, lis, dims in progress(todo, len(todo), "rooms"):
        walls, floor, ceiling = mats[:3]
        h_peer, h, t_peer, t_bake, t_render = [], [], 0.0, 0.0, 0.0
        for k in range(realisations):
            t0 = time.perf_counter()
            h_peer.append(_pra_polygon(corners, H, walls, floor, ceiling, src, lis, rays, seed + k, *mats[3:],
                                       min_scattering=min_scattering))
            t_peer += (time.perf_counter() - t0) / realisations
            y, tb, tr = _ours(spec, src, lis, seconds, scattering, er_order, per_room, er_images, realisation=k,
                              tail_edt=tail_edt, tail_buildup=tail_buildup, neighbour_tails=neighbour_tails,
                              reverb=reverb, tail_beam=tail_beam, min_scattering=min_scattering)
            h.append(y)
            t_bake, t_render = t_bake + tb / realisations, t_render + tr / realisations
        t_dir = _onset(spec, src, lis)  # both from the shortest open path's time (the peer's filter: 40 samples on)
        ours, peer = room_parameters(h, t_dir=t_dir), room_parameters(h_peer, t_dir=t_dir + PRA_DELAY)
        row = {"case": name, "scene": spec, "source": list(src), "listener": list(lis), "bands_hz": list(BANDS),
               "ours": ours, "pyroomacoustics": peer, "vs_pyroomacoustics": _errors(ours, peer, "diffuse" in name),
               "time_s": {"ours_bake": round(t_bake, 3), "ours_render": round(t_render, 3),
                          "ours_realtime_fraction": round(t_render / seconds, 4),
                          "pyroomacoustics": round(t_peer, 3)}}
        e_ours, e_peer = window_energies(h, t_dir=t_dir), window_energies(h_peer, t_dir=t_dir + PRA_DELAY)
        gone = np.minimum(e_ours / e_ours.sum(1, keepdims=True), e_peer / e_peer.sum(1, keepdims=True)) < 1e-9
        diff = np.round(10 * np.log10(np.maximum(e_ours, 1e-300) / np.maximum(e_peer, 1e-300)), 1)
        row["windows"] = {"ms": list(WINDOWS_MS), "ours_minus_peer_db": [  # None: a response 90 dB down there
            [None if g else float(v) for v, g in zip(dr, gr)] for dr, gr in zip(diff, gone)]}
        if dims is not None:
            row["theory"] = _theory_shoebox(dims, walls, floor, ceiling, src, lis)
        cases.append(row)
    sealed = (_sealed(scattering, per_room, tail_edt, tail_buildup, reverb, tail_beam)
              if (case is None or "sealed" in case.lower()) and not min_scattering else None)
    met = {k: sum(c["vs_pyroomacoustics"][k]["met"] for c in cases) for k in TARGETS}
    out = {"bench": "fidelity", "peer": "pyroomacoustics hybrid (ISM order 3 + ray tracing, "
           f"{rays} rays, receiver radius 0.5 m, seed {seed})", "realisations": realisations, "sample_rate": FS, "scattering": scattering, "er_order": er_order,
           "er_images": er_images, "per_room": per_room, "tail_edt": tail_edt,
           "tail_buildup": tail_buildup, "tail_beam": tail_beam,
           "neighbour_tails": neighbour_tails, "reverb": reverb, "min_scattering": min_scattering, "case": case,
           "onset": f"the direct sound's time along the shortest open path (the peer's {PRA_DELAY} samples later)",
           "cases": cases,
           "sealed": sealed,
           "targets_met": {k: f"{v}/{len(cases)}" for k, v in met.items()}}
    if plot:
        _plot(cases, plot, realisations)
        out["plot"] = plot
    return out


def _plot(cases: list, path: str, realisations: int = 1) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 4, figsize=(18, 4.5))
    for ax, k in zip(axs, ("G", "T30", "EDT", "C50")):
        for i, c in enumerate(cases):
            a = np.array([np.nan if v is None else v for v in c["ours"][k]], float)
            b = np.array([np.nan if v is None else v for v in c["pyroomacoustics"][k]], float)
            ax.plot(b, a, "os^"[i // 10 % 3], color=f"C{i % 10}", label=c["case"])  # 10 colours, then a new marker
        lo = np.nanmin([ax.get_xlim()[0], ax.get_ylim()[0]])
        hi = np.nanmax([ax.get_xlim()[1], ax.get_ylim()[1]])
        ax.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        ax.set_xlabel(f"{k}, pyroomacoustics")
        ax.set_ylabel(f"{k}, ours")
        ax.set_title(k + " (250 Hz - 4 kHz)")
    axs[0].legend(fontsize=6)
    if realisations > 1:
        fig.suptitle(f"expected responses: the mean band energies of {realisations} realisations of each model")
    fig.tight_layout()
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)  # the argument's promise: created when writing
    fig.savefig(path, dpi=90)
    plt.close(fig)
