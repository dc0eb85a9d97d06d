"""Early reflections: image sources of the listener's room's own walls (Borish 1984), or of a probe's proxy box
(Allen & Berkley 1979).

A room with a footprint polygon of at most ``MAX_WALLS`` sides, vertical walls and a flat floor and ceiling
(``RenderConfig(er_images="room")``, the default) is imaged in its own walls and in those of the rooms it opens
into (up to ``MAX_NEIGHBOURS``, by open area): every sequence of reflectors up to the order, kept when the path
traced back from the listener meets each reflector inside its extent and every leg passes walls only through their
openings (an L-shaped room's inner corner hides some images and shows others; the next room's walls reflect
through the doorway). Each wall's reflection factor is sampled along and up it by rays, so a doorway reflects
nothing and lets sound through, a closed door reflects and blocks, and a window reflects as glass. Elsewhere (a
room with more walls, a listener in no room, ``er_images="box"``) the images are those of the proxy box below.

For a box [lo, hi] and a source inside it, the image positions along each axis are x' = (1 - 2q) x + 2 m L
(box-local coordinates, q in {0, 1}, m integer); such an image has reflected |m - q| times off the low wall and
|m| times off the high wall of that axis. All images up to a reflection ``order`` are enumerated once per order
(the lattice); ``kernels.image_taps`` places them for every source each block. A wall reflects sqrt(1 - alpha) of the
amplitude, alpha its material's mean absorption over 500 Hz - 2 kHz; an open side (no surface within reach of the
probe) reflects nothing.
"""
from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np

from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS, get_material

MID_BANDS = (BANDS >= 500) & (BANDS <= 2000)


@lru_cache(maxsize=8)
def lattice(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q (K, 3), m (K, 3) and the reflection counts (K, 6) (-x, +x, -y, +y, -z, +z) of every image with
    1 <= total reflections <= order."""
    qs, ms, counts = [], [], []
    rng = range(-order, order + 1)
    for q in itertools.product((0, 1), repeat=3):
        for m in itertools.product(rng, repeat=3):
            c = []
            for a in range(3):
                c += [abs(m[a] - q[a]), abs(m[a])]
            if 1 <= sum(c) <= order:
                qs.append(q)
                ms.append(m)
                counts.append(c)
    return np.array(qs, float), np.array(ms, float), np.array(counts, float)


def wall_reflectance(materials) -> np.ndarray:
    """Amplitude reflection factor (6,) of the proxy box's walls (-x, +x, -y, +y, -z, +z)."""
    r = []
    for name in materials:
        if name == "Transparent":
            r.append(0.0)
        else:
            a = float(np.mean(np.asarray(get_material(name).absorption)[MID_BANDS]))
            r.append(np.sqrt(max(0.0, 1.0 - a)))
    return np.array(r)


MAX_WALLS = 12  # a room with more walls (a segmented outline's staircase) is imaged as its probe's box
MAX_NEIGHBOURS = 3  # rooms imaged with the listener's: those joined to it by the most open area
WALL_SAMPLES = (128, 8)  # reflection factors sampled along and up each wall


def sequences(reflectors: int, order: int) -> np.ndarray:
    """Every sequence of 1..order of the reflectors (0..reflectors - 1), none twice in a row: (M, order) int64,
    -1 padded."""
    rows = [[p] + [-1] * (order - 1) for p in range(reflectors)]
    if order == 2:
        rows += [[p, q] for p in range(reflectors) for q in range(reflectors) if q != p]
    return np.array(rows, np.int64).reshape(-1, order)


class RoomWalls:
    """One room's surfaces for image sources: its walls from the footprint polygon (vertical between its floor and
    ceiling), plan segments ``edges`` (E, 4) with outward ``normal`` (E, 2), each wall's amplitude reflection factor
    sampled along and up it by rays (``table`` (E, T, Z): 0 where the rays meet nothing, an opening such as a
    doorway), the floor's and ceiling's (``rf``, ``rc``). Samples within reach of a door leaf (``near_door``) are
    cast again through the scene's dynamic geometry when a door moves (:meth:`refresh`): a closed door reflects
    and blocks, an open one lets sound through. Where the room opens into others (:meth:`opens_into`) comes from
    the static structure alone, so a door shut when the renderer is built still joins its rooms once opened."""

    def __init__(self, room, caster, doors=()):
        from sonicverse_core.scene.materials import MATERIAL_NAMES
        from sonicverse_core.scene.model import points_in_polygon

        poly = np.asarray(room.footprint, float)
        self.room, self.caster = room, caster
        a, b = poly, np.roll(poly, -1, axis=0)
        self.edges = np.hstack([a, b])
        d = b - a
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        self.normal = np.stack([d[:, 1], -d[:, 0]], 1) / length[:, None]  # counter-clockwise: outward
        self.zf, self.zc = float(room.z_floor), float(room.z_ceiling)
        T, Z = WALL_SAMPLES
        self._refl = np.array([wall_reflectance([m])[0] for m in MATERIAL_NAMES] + [0.0])  # index -1: no hit
        t = (np.arange(T) + 0.5) / T
        z = self.zf + (np.arange(Z) + 0.5) / Z * (self.zc - self.zf)
        # rays from 0.25 m in front of each sample point out through it: a surface within 0.35 m is the wall there
        pt = a[:, None, :] + t[None, :, None] * d[:, None, :]  # (E, T, 2)
        E = len(a)
        self._o = np.concatenate([np.broadcast_to((pt - 0.25 * self.normal[:, None, :])[:, :, None, :], (E, T, Z, 2)),
                                  np.broadcast_to(z[None, None, :, None], (E, T, Z, 1))], axis=-1).reshape(-1, 3)
        self._d = np.repeat(np.c_[self.normal, np.zeros(E)], T * Z, axis=0)
        near = np.zeros(len(self._o), bool)
        self.doors_near = set()  # the doors (names) whose leaves reach some of these walls' samples
        for door in doors:  # within a leaf's reach of its hinge
            reach = np.hypot(*(self._o[:, :2] - np.asarray(door.hinge, float)).T) < door.width + 0.5
            near |= reach
            if reach.any():
                self.doors_near.add(door.name)
        self.near_door = np.flatnonzero(near)
        self.table = self._cast(np.arange(len(self._o)), dynamic=False).reshape(E, T, Z)
        # the static structure's first hit of the samples near doors, kept: a door's move casts them through the
        # dynamic geometry alone and takes the nearer hit (the same answer as casting both again)
        self._near_static = caster.static.first_hit(self._o[self.near_door], self._d[self.near_door], 0.6)
        self._near_still = (None, None)  # (the still objects' build, the nearer of their hits and the static's)
        self._near_max = np.full(len(self.near_door), 0.6)
        self._open = self.table.reshape(-1) == 0  # openings of the structure, whatever state the doors are in
        self.refresh()
        # floor and ceiling: rays down and up from points inside the footprint
        lo, hi = poly.min(0), poly.max(0)
        g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 7)[1:-1], np.linspace(lo[1], hi[1], 7)[1:-1]), -1)
        g = g.reshape(-1, 2)
        g = g[points_in_polygon(g, poly)]
        if not len(g):
            g = poly.mean(0, keepdims=True)
        zm = 0.5 * (self.zf + self.zc)
        for side, sign in (("rf", -1.0), ("rc", 1.0)):
            o = np.c_[g, np.full(len(g), zm)]
            h = caster.static.first_hit(o, np.tile([0.0, 0.0, sign], (len(g), 1)), 0.5 * (self.zc - self.zf) + 0.1)
            setattr(self, side, float(np.mean(self._refl[np.where(h.hit, h.material, -1)])))

    def _cast(self, idx: np.ndarray, dynamic: bool) -> np.ndarray:
        h = self.caster.first_hit(self._o[idx], self._d[idx], 0.6, include_dynamic=dynamic)
        return self._refl[np.where(h.hit & (h.distance <= 0.35), h.material, -1)]

    def refresh(self) -> None:
        """Cast the samples near doors again, through the doors as they are now (the dynamic geometry only; the
        static structure's hits of them were kept)."""
        if not len(self.near_door):
            return
        hits = self._near_static
        if self.caster.scene.objects:
            dyn = self.caster.dynamic
            o, d = self._o[self.near_door], self._d[self.near_door]
            if self._near_still[0] != dyn.builds["still"]:  # the objects that have not moved: cast once per build
                self._near_still = (dyn.builds["still"], hits.nearer(dyn.first_hit(o, d, 0.6, groups=("still",))))
            hits = self._near_still[1]
            f, t = dyn.faces(o, d, self._near_max, groups=("movers",))  # the doors and whatever else has moved
            closer = (f >= 0) & (t < hits.distance)
            dist = np.where(closer, t, hits.distance)
            mat = np.where(closer, dyn.mesh.face_material[np.maximum(f, 0)], hits.material)
        else:
            dist, mat = hits.distance, hits.material
        self.table.reshape(-1)[self.near_door] = self._refl[np.where(dist <= 0.35, mat, -1)]

    def opens_into(self, rooms) -> dict:
        """{index in ``rooms``: open area (m^2)} of the rooms this one's openings in the static structure (doorways,
        open or shut) lead into (0.3 m beyond each open sample of its walls)."""
        T, Z = WALL_SAMPLES
        open_ = self._open
        beyond = self._o[:, :2] + 0.55 * self._d[:, :2]
        cell = (np.linalg.norm(self.edges[:, 2:] - self.edges[:, :2], axis=1) / T * (self.zc - self.zf) / Z)
        area = np.repeat(cell, T * Z)
        out = {}
        for k, room in enumerate(rooms):
            if room is self.room:
                continue
            inside = open_ & room.contains(beyond)
            if inside.any():
                out[k] = float(area[inside].sum())
        return out


class RoomImages:
    """The image sources' geometry for a listener in ``rooms[0]``: its walls and those of the rooms it opens into
    (``rooms[1:]``), pooled: ``edges`` (E, 4), ``normal`` (E, 2), ``table`` (E, T, Z), each wall's floor and ceiling
    heights ``zwall`` (E, 2); per room its walls ``first[r]:first[r + 1]``, floor and ceiling heights ``zf``,
    ``zc`` and factors ``rf``, ``rc``; reflectors 0..E-1 the walls, E + 2r room r's floor, E + 2r + 1 its ceiling;
    ``seqs`` the reflector sequences up to the order."""

    def __init__(self, walls: list, order: int):
        self.walls = walls
        self.room = walls[0].room
        self.edges = np.vstack([w.edges for w in walls])
        self.normal = np.vstack([w.normal for w in walls])
        self.zwall = np.vstack([np.tile([w.zf, w.zc], (len(w.edges), 1)) for w in walls])
        self.first = np.cumsum([0] + [len(w.edges) for w in walls]).astype(np.int64)
        self.zf = np.array([w.zf for w in walls])
        self.zc = np.array([w.zc for w in walls])
        self.rf = np.array([w.rf for w in walls])
        self.rc = np.array([w.rc for w in walls])
        self.table = np.zeros((len(self.edges),) + WALL_SAMPLES)
        self.update()
        self.seqs = sequences(len(self.edges) + 2 * len(walls), order)

    def update(self) -> None:
        """Copy the rooms' wall tables in (after :meth:`RoomWalls.refresh`)."""
        for w, a in zip(self.walls, self.first[:-1]):
            self.table[a:a + len(w.edges)] = w.table


def image_amplitudes(reflect: np.ndarray, order: int) -> np.ndarray:
    """Amplitude factor (K,) of every image of the lattice: the product of its walls' reflection factors
    (the image positions themselves are placed per block by ``kernels.image_taps``)."""
    c = lattice(order)[2]
    return np.prod(np.where(c > 0, reflect[None, :] ** c, 1.0), axis=1)


class EarlyState(PerSource):
    """A listener's early reflections: per source and image the previous block's delay, gain and second-order
    spherical-harmonic weights (``delay``, ``gain``, ``Y``) and this block's (``*_new``); the block's ambisonic
    signals (``amb``), the binaural decoder's overlap-save history and transforms (``hist``, ``fft``, ``A``,
    ``acc``, ``ifft``) and its output ``y``; the probe whose box is imaged (``probe``, found at ``probe_key``) or the room
    whose walls are (``room``, a :class:`RoomImages`)."""

    __slots__ = ("delay", "gain", "Y", "delay_new", "gain_new", "Y_new", "amb", "tmp", "hist", "fft", "A", "acc",
                 "ifft", "y", "probe_key", "probe", "room", "pts")

    def __init__(self, cap: int, K: int, C: int, block: int, nfft: int):
        rows = (("delay", (K,), np.float64, 0), ("gain", (K,), np.float64, 0), ("Y", (K, C), np.float64, 0),
                ("delay_new", (K,), np.float64, 0), ("gain_new", (K,), np.float64, 0),
                ("Y_new", (K, C), np.float64, 0))
        super().__init__(cap, rows)
        self.amb = np.zeros((C, block), np.float32)
        self.tmp = np.zeros(block, np.float32)
        self.hist = self.fft = self.A = self.acc = self.ifft = None
        self.probe_key, self.probe, self.room = None, -1, None
        self.pts = np.zeros((3, 3))  # the room images' scratch: a source and its images
        if nfft:  # decoded binaurally
            from sonicverse_core.acoustics.fft import irfft_plan, rfft_plan

            self.hist = np.zeros((C, nfft), np.float32)
            self.fft, self.A = rfft_plan(self.hist)
            self.acc = np.zeros((2, nfft // 2 + 1), np.complex64)
            self.ifft, self.y = irfft_plan(self.acc, nfft)
        else:
            self.y = np.zeros((2, block), np.float32)


class EarlyReflections:
    """The early-reflection subsystem of ``renderer`` (:mod:`sonicverse_core.acoustics.state`): image sources (order
    1 or 2) of the proxy box of the probe nearest the listener in its room, from the actual source and listener
    positions, each a ramped fractional-delay tap encoded in second-order ambisonics in the head frame and decoded
    binaurally by least-squares spherical-harmonic HRTF filters (or to stereo / mono)."""

    name = "early"
    ORDER = 2  # the ambisonic order

    def __init__(self, renderer):
        self.r = r = renderer
        cfg, scene, probes = r.cfg, r.scene, r.probes
        B, fs = cfg.block, cfg.sample_rate
        # rooms imaged in their own walls, each with the rooms it opens into
        self.room_images, self.walls, self._doors, self._door_poses = {}, [], [], []
        self._version = scene.dynamic_version if scene is not None else 0
        self._stale: set = set()  # doors moved, their walls not cast again yet (render: in the block after)
        if cfg.er_images == "room" and scene is not None and scene.rooms:
            from sonicverse_core.scene.model import Door

            rooms = [room for room in scene.rooms
                     if 3 <= len(room.footprint) <= MAX_WALLS and room.z_ceiling > room.z_floor]
            if rooms:
                if r.occlusion is not None:
                    caster = r.occlusion.caster
                else:
                    from sonicverse_core.geometry.raycast import SceneRayCaster

                    caster = SceneRayCaster(scene)
                self._doors = [o for o in scene.objects if isinstance(o, Door)]
                self._door_poses = [d.pose.tobytes() for d in self._doors]
                self.walls = [RoomWalls(room, caster, self._doors) for room in rooms]
                # a footprint that is not where the walls are (a bounding box of a mesh scene): no room images
                self.walls = [w for w in self.walls if np.mean(w.table > 0) >= 0.5]
                rooms = [w.room for w in self.walls]
                for w in self.walls:
                    near = sorted(w.opens_into(rooms).items(), key=lambda kv: -kv[1])[:MAX_NEIGHBOURS]
                    self.room_images[id(w.room)] = RoomImages([w] + [self.walls[k] for k, _ in near], cfg.er_order)
        self.K = max([len(lattice(cfg.er_order)[0])] + [len(g.seqs) for g in self.room_images.values()])
        self.C = (self.ORDER + 1) ** 2
        self.refl = [wall_reflectance(p.box_materials) for p in probes]
        self.probe_rooms = [scene.room_at(p.position[:2]) if scene is not None and scene.rooms else None
                            for p in probes]
        # the image sources' box: the probe's proxy box within its room's footprint (rays from a probe that
        # faces a doorway run on into the next room; the room's walls are where the reflections are)
        self.box = []
        for p, room in zip(probes, self.probe_rooms):
            lo, hi = p.box_lo.copy(), p.box_hi.copy()
            if room is not None:
                lo[:2] = np.maximum(lo[:2], room.footprint.min(0))
                hi[:2] = np.minimum(hi[:2], room.footprint.max(0))
                if np.any(hi <= lo) or np.any(p.position < lo) or np.any(p.position > hi):
                    lo, hi = p.box_lo, p.box_hi
            self.box.append((lo, hi))
        self.amp = {}
        self.hrtf = r.hrtf
        if self.hrtf is not None:
            taps = self.hrtf.taps
            # 2nd-order SH smooths the HRTF above ~2 kHz anyway: 3 ms of filter (interaural delay included)
            er_len = int(0.003 * fs)
            max_rel = int(np.ceil((self.hrtf.onsets.max() - self.hrtf.onsets.min()) * fs))
            self.nfft = 1 << int(np.ceil(np.log2(B + er_len + 16)))
            big = 1 << int(np.ceil(np.log2(taps + max_rel + 64)))
            self.filters, self.bulk = self.hrtf.ambisonic_filters(self.ORDER, max(big, self.nfft), er_len)
            if big > self.nfft:
                h = np.fft.irfft(self.filters, big, axis=-1)[..., :er_len]
                self.filters = np.fft.rfft(h, self.nfft, axis=-1).astype(np.complex64)
        else:
            self.nfft, self.bulk = 0, 0.0
            dec = np.zeros((2, self.C))
            dec[:, 0] = 0.5 if cfg.output == "stereo" else np.sqrt(0.5)
            if cfg.output == "stereo":
                dec[:, 1] = [0.5 / np.sqrt(3), -0.5 / np.sqrt(3)]
            self.decode = dec.astype(np.float32)

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> EarlyState:
        return EarlyState(cap, self.K, self.C, self.r.cfg.block, self.nfft)

    def grow(self, st: EarlyState | None, cap: int) -> None:
        if st is not None:
            st.grow(cap)

    def max_delay(self) -> float:
        from sonicverse_core.acoustics.probes import SPEED_OF_SOUND

        r = self.r
        size = [np.max(p.box_hi - p.box_lo) for p in r.probes]
        size += [np.hypot(*np.ptp(g.edges.reshape(-1, 2), axis=0)) + np.ptp(g.zwall) for g in self.room_images.values()]
        return r.direct.max_delay() + 3 * r.cfg.er_order * float(np.max(size)) / SPEED_OF_SOUND

    def reset(self, st: EarlyState) -> None:
        st.amb[:] = 0
        if st.hist is not None:
            st.hist[:] = 0
            st.acc[:] = 0

    def nearest_probe(self, st: EarlyState, p: np.ndarray) -> int:
        """The probe for the listener's early reflections: the nearest one in the listener's room (the nearest
        overall where the room is unknown or has none); cached per listener while it stays within 5 cm."""
        from sonicverse_core.acoustics.kernels import farther

        r = self.r
        if st.probe_key is None or farther(st.probe_key, p, 0.05):
            d2 = np.sum((r._probe_pos - p) ** 2, axis=1)
            if r.coupling is not None:  # the slice's room labels: a lookup, not polygon tests
                room = r.coupling.room_of(p[None, :2])[0]
                room = r.coupling.rooms[room] if room >= 0 else None
            else:
                room = r.scene.room_at(p[:2]) if r.scene is not None and r.scene.rooms else None
            same = np.array([q is not None and q is room for q in self.probe_rooms]) if room is not None else None
            if same is not None and same.any():
                d2 = np.where(same, d2, np.inf)
            st.probe_key, st.probe = p.copy(), int(np.argmin(d2))
            st.room = self.room_images.get(id(room)) if room is not None else None
        return st.probe

    def render(self, st: EarlyState, ls, lis, out) -> None:
        """Image sources of the listener's room's walls (of the nearest probe's box where its room is not imaged),
        added into ``out``. A room's images come from where each source is: one outside the room has none (its
        sound comes in along its path and by the coupled late reverb). A box's come from ``ls.pos``, the emitters
        (a source heard along a path is imaged from where its path puts it), scaled by the mid-band transmission."""
        from sonicverse_core.acoustics.early_kernels import room_image_taps
        from sonicverse_core.acoustics.kernels import accumulate_sh, add_tail, encode_taps, image_taps, shift_left
        from sonicverse_core.acoustics.probes import SPEED_OF_SOUND

        r, n = self.r, ls.n
        cfg, B = r.cfg, r.cfg.block
        k = self.nearest_probe(st, lis.position)
        delay, gain, Y = st.delay_new[:n], st.gain_new[:n], st.Y_new[:n]
        pd, pg, pY = st.delay[:n], st.gain[:n], st.Y[:n]
        g = st.room
        if g is not None:
            if self._stale:  # doors that moved before the last block: the walls they reach are cast again now
                for w in self.walls:
                    if w.doors_near & self._stale:
                        w.refresh()
                for ri in self.room_images.values():
                    ri.update()
                self._stale = set()
            if r.scene.dynamic_version != self._version:  # something moved; if a door did, its walls are cast again
                self._version = r.scene.dynamic_version  # in the next block (a door's cost spread over the blocks
                doors = [d.pose.tobytes() for d in self._doors]  # after it: the occlusion and paths first)
                if doors != self._door_poses:
                    self._stale |= {d.name for d, a, b in zip(self._doors, self._door_poses, doors) if a != b}
                    self._door_poses = doors
            M = len(g.seqs)
            room_image_taps(r._pos[:n], ls.mute[:n], g.seqs, g.edges, g.normal, g.table, g.zwall, g.first, g.zf,
                            g.zc, g.rf, g.rc, lis.position, ls.R, *r._rolloff, self.bulk, SPEED_OF_SOUND, st.pts,
                            delay[:, :M], gain[:, :M], Y[:, :M], pd[:, :M], pg[:, :M], pY[:, :M])
        else:
            if k not in self.amp:
                self.amp[k] = image_amplitudes(self.refl[k], cfg.er_order)
            q, m, _ = lattice(cfg.er_order)
            lo, hi = self.box[k]
            M = len(q)
            image_taps(ls.pos, lo, hi, q, m, self.amp[k], lis.position, ls.R, *r._rolloff, ls.occ[:n], self.bulk,
                       SPEED_OF_SOUND, delay[:, :M], gain[:, :M], Y[:, :M])
        if M < self.K:  # slots the current images do not use fade out
            gain[:, M:] = 0.0
            delay[:, M:] = pd[:, M:]
            Y[:, M:] = pY[:, M:]
        fresh = ls.fresh[:n]
        if ls.any_fresh:
            pd[fresh], pg[fresh], pY[fresh] = delay[fresh], gain[fresh], Y[fresh]
        amb = st.amb
        encode_taps(r._ring, r.write - B, pd, delay, float(cfg.sample_rate), pg, gain, pY, Y, r._ramp, amb, st.tmp)
        st.delay, st.delay_new = st.delay_new, st.delay
        st.gain, st.gain_new = st.gain_new, st.gain
        st.Y, st.Y_new = st.Y_new, st.Y
        if self.hrtf is None:
            np.matmul(self.decode, amb, out=st.y)
            add_tail(st.y, 1.0, out)
            return
        h = st.hist
        shift_left(h, B)
        h[:, -B:] = amb
        st.fft.run()
        accumulate_sh(st.A, self.filters, st.acc)
        st.ifft.run()
        add_tail(st.y, 1.0 / self.nfft, out)
