"""Coupled rooms: how much of a source's reverberant energy reaches the other rooms, per band.

Statistical energy balance (see the module's references in ``between-rooms`` theory): room i with absorption area
A_i (Sabine, from its probes' baked RT60 and its volume: A = 0.161 V / T) exchanges energy with room j through
K_ij = sum of S tau over the elements they share:

* doorways (the scene's doors, between the rooms each names): the open part of the leaf's area with tau = 1 (the
  aperture fraction of :meth:`PathGraph.apertures`), the rest through the leaf's material;
* openings found on the ear-height slice where the free space of two rooms touches (mesh scenes, which have no
  door objects): their width x 2 m (or the lower ceiling) with tau = 1;
* walls: the length of boundary the two rooms share on the slice (free cells of one room within 0.6 m of the other)
  x the lower ceiling, with the transmission per band of the materials a ray between them crosses (mass law).

Per band: (A_i + sum_j K_ij) E_i - sum_j K_ij E_j = W_i; a source of unit power in room s gives energies E; the
listener's room l receives E_l / E_s of the source room's reverberant energy. For two rooms with S tau << A this is
the textbook D = TL - 10 log10(S / A_2).

A room's own absorption A_i comes from its probes' RT60. A probe baked for its own room (``Probe.room``: rays that
left through an opening were lost) decays as if its doorways and openings absorbed everything, so their area is
taken off: A_i = 0.161 V / T - S_open (at least a tenth of 0.161 V / T). In the two reference rooms with stochastic
scattering this gives 4.12 m^2 at 1 kHz where the same room sealed bakes 4.04 m^2; with vector scattering the
doorway takes less than its area (1.2 of 1.8 m^2: few rays graze it), so A_i comes out low. A probe baked over the
whole connected space gives A_i = 0.161 V / T as it is.

Decay (:meth:`RoomCoupling.late_split`): the same balance in time, V_i dE_i/dt = -(c / 4) (M E)_i with
M = diag(A + sum_j K) - K, has one decay rate per eigenmode (per band). After a source in room s stops, room l's
energy is a sum of those modes. The slowest mode is the late slope of coupled rooms: the live room's decay heard in
a dead room beside it, or two like rooms ringing together, slower than either with its doorway absorbing
(Summers, JASA 2004, statistical-acoustics models of coupled rooms). Its share of room l's energy goes to a tail
that decays as slowly; the rest decays as room l alone.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from sonicverse_core.acoustics.paths import remember
from sonicverse_core.scene.materials import BANDS, material_arrays

OPENING_HEIGHT = 2.0
_SPLITS = [0]  # late splits made in this process: each one's "gen", a key that never repeats


class RoomCoupling:
    def __init__(self, scene, graph, probes):
        self.scene, self.graph = scene, graph
        self.rooms = list(scene.rooms)
        R = len(self.rooms)
        self.index = {r.name: k for k, r in enumerate(self.rooms)}
        rt_all = np.mean([p.rt60 for p in probes], axis=0) if probes else np.full(len(BANDS), 0.5)
        self.A = np.zeros((R, len(BANDS)))
        for k, r in enumerate(self.rooms):
            mine = [p.rt60 for p in probes or [] if r.contains(p.position[:2])[0]]
            rt = np.mean(mine, axis=0) if mine else rt_all
            self.A[k] = 0.161 * max(r.volume, 1.0) / np.maximum(rt, 0.05)
        self.V = np.array([max(r.volume, 1.0) for r in self.rooms])
        self.walls = np.zeros((R, R, len(BANDS)))  # S tau through walls (and openings of mesh scenes)
        self.open_area = np.zeros((R, R))  # openings found on the slice (mesh scenes), m^2
        # which room every cell of the path graph's slice is in (-1: none): a real-time lookup, not polygon tests
        ny, nx = graph.shape
        centres = graph.origin + (np.argwhere(np.ones((ny, nx), bool))[:, ::-1] + 0.5) * graph.cell
        labels = np.full(ny * nx, -1)
        for k, r in enumerate(self.rooms):
            labels[(labels < 0) & r.contains(centres)] = k
        self.labels = labels.reshape(ny, nx)
        self._slice_coupling()
        # a probe baked for its own room lost what left through its doorways and openings: that area is not the
        # room's own absorption (the coupling K carries it)
        self.S_open = self.open_area.sum(1)
        for d in self.graph.doors:
            for name in d.rooms:
                if name in self.index:
                    self.S_open[self.index[name]] += d.width * OPENING_HEIGHT
        for k, r in enumerate(self.rooms):
            if any(p.room == r.name for p in probes or []):
                self.A[k] = np.maximum(self.A[k] - self.S_open[k], 0.1 * self.A[k])
        self._cache: dict = {}  # door state (apertures) -> transfer (the last DOOR_STATES met)
        self._split: dict = {}  # door state -> late_split (the same)
        self._T_now = self._split_now = None
        self._version = self._split_version = None

    def _slice_coupling(self) -> None:
        g, R = self.graph, len(self.rooms)
        if R < 2:
            return
        ny, nx = g.shape
        ij = np.argwhere(~g.blocked)
        centres = g.origin + (ij[:, ::-1] + 0.5) * g.cell
        masks = []
        for r in self.rooms:
            m = np.zeros(g.shape, bool)
            m[ij[:, 0], ij[:, 1]] = r.contains(centres)
            masks.append(m)
        trans = material_arrays()[2]
        boundary = [m & ndimage.binary_dilation(g.blocked, np.ones((3, 3), bool)) for m in masks]
        door_rooms = {frozenset(d.rooms) for d in g.doors}
        edt = [ndimage.distance_transform_edt(~m, return_indices=True) for m in masks]  # once per room
        near = [d * g.cell for d, _ in edt]
        for a in range(R):
            for b in range(a + 1, R):
                h = min(self.rooms[a].z_ceiling - self.rooms[a].z_floor, self.rooms[b].z_ceiling - self.rooms[b].z_floor)
                # openings: free cells of one room next to free cells of the other (no wall between)
                touch = masks[a] & ndimage.binary_dilation(masks[b], np.ones((3, 3), bool))
                if touch.any() and frozenset((self.rooms[a].name, self.rooms[b].name)) not in door_rooms:
                    width = max(np.count_nonzero(touch), 1) * g.cell
                    self.walls[a, b] += width * min(OPENING_HEIGHT, h)
                    self.open_area[a, b] = self.open_area[b, a] = width * min(OPENING_HEIGHT, h)
                shared = [boundary[a] & (near[b] < 0.6), boundary[b] & (near[a] < 0.6)]
                n_cells = 0.5 * (np.count_nonzero(shared[0]) + np.count_nonzero(shared[1]))
                if n_cells == 0:
                    continue
                # the wall's transmission: rays at ear height from up to 24 shared cells of a to the nearest cells of
                # b; a ray that crosses nothing went through an opening (a door's, counted with the door)
                pa = np.argwhere(shared[0])
                pa = pa[np.linspace(0, len(pa) - 1, min(24, len(pa))).astype(int)]
                ib, jb = edt[b][1]
                pb = np.c_[ib[pa[:, 0], pa[:, 1]], jb[pa[:, 0], pa[:, 1]]]
                xa = np.c_[g.origin + (pa[:, ::-1] + 0.5) * g.cell, np.full(len(pa), g.z)]
                xb = np.c_[g.origin + (pb[:, ::-1] + 0.5) * g.cell, np.full(len(pb), g.z)]
                cr = self._caster().crossings(xa, xb, include_dynamic=False)
                taus = []
                for ray in np.unique(cr.ray):
                    sel = np.flatnonzero(cr.ray == ray)
                    _, first = np.unique(cr.part[sel], return_index=True)
                    taus.append(np.prod(trans[cr.material[sel[first]]], axis=0))
                if taus:
                    self.walls[a, b] += n_cells * g.cell * h * len(taus) / len(pa) * np.mean(taus, axis=0)
        self.walls += self.walls.transpose(1, 0, 2)

    def _caster(self):
        if getattr(self, "_rc", None) is None:
            from sonicverse_core.geometry.raycast import SceneRayCaster

            self._rc = SceneRayCaster(self.scene)
        return self._rc

    def coupling(self) -> np.ndarray:
        """K (R, R, 9): S tau between every pair of rooms, the doors as they are now."""
        K = self.walls.copy()
        trans = material_arrays()[2]
        from sonicverse_core.scene.materials import MATERIAL_INDEX

        for d, ap in zip(self.graph.doors, self.graph.apertures()):
            if len(d.rooms) != 2 or any(r not in self.index for r in d.rooms):
                continue
            a, b = (self.index[r] for r in d.rooms)
            area = d.width * OPENING_HEIGHT
            k = area * (ap + (1 - ap) * trans[MATERIAL_INDEX[d.material]])
            K[a, b] += k
            K[b, a] += k
        return K

    def transfer(self) -> np.ndarray:
        """(R, R, 9) amplitude: sqrt(E_l / E_s) for a source in room s heard in room l, the doors as they are now
        (cached per door state)."""
        if self._version == self.scene.dynamic_version and self._T_now is not None:
            return self._T_now
        self._version = self.scene.dynamic_version
        key = tuple(np.round(self.graph.apertures(), 4))
        T = self._cache.get(key)
        if T is None:
            E = np.linalg.inv(self._balance(self.coupling()))  # (9, R, R); column s: a unit source in room s
            d = np.diagonal(E, axis1=1, axis2=2)  # (9, R)
            T = np.ascontiguousarray(np.sqrt(np.maximum(E / d[:, None, :], 0.0)).transpose(2, 1, 0))  # [s, l, band]
        remember(self._cache, key, T)
        self._T_now = T
        return T

    def _balance(self, K: np.ndarray) -> np.ndarray:
        """(9, R, R) per band the energy balance's matrix M = diag(A_i + sum_j K_ij) - K for couplings K (R, R, 9)."""
        Kb = K.transpose(2, 0, 1)
        M = -Kb
        i = np.arange(len(self.rooms))
        M[:, i, i] += self.A.T + Kb.sum(2)
        return M

    def open_share(self) -> np.ndarray:
        """(R,) the part of each room's doorway and opening area that is open now (1 for a room without any)."""
        now = self.open_area.sum(1)
        for d, ap in zip(self.graph.doors, self.graph.apertures()):
            for name in d.rooms:
                if name in self.index:
                    now[self.index[name]] += ap * d.width * OPENING_HEIGHT
        return np.where(self.S_open > 0, now / np.maximum(self.S_open, 1e-9), 1.0)

    def late_split(self) -> dict:
        """The coupled late decay, the doors as they are now (cached per door state):

        * ``energy`` (R_s, R_l, 9): reverberant energy in room l for a unit-power source in room s, as a multiple of
          the direct sound's at 1 m: 16 pi [M^-1]_ls (16 pi / A for one room alone);
        * ``slow`` (R_s, R_l, 9): the share of it in the slowest decay mode (0..1);
        * ``slow_rt`` (9,): that mode's RT60 (s), and ``slow_room``: the room it rings in most (at 1 kHz);
        * ``own_rt`` (R, 9): each room's decay alone with its doorways as they are now (open ones absorb);
        * ``modes_rt`` (R_k, 9), ``modes_share`` (R_k, R_s, R_l, 9), ``modes_room`` (R_k,): every mode, slowest
          first (the k-th slowest in each band): its RT60, its share of room l's energy for a source in room s, and
          the room it rings in most (at 1 kHz); mode 0 is ``slow_rt`` / ``slow`` / ``slow_room``;
        * ``buildup_tau`` (R_s, R_l): how fast room l fills with the energy of a source in room s (s; 0 where s =
          l): the two rooms' own balance, 1 / (lam_1 - lam_0) of its two modes (E_l(t) proportional to
          e^(-lam_0 t) - e^(-lam_1 t)), their other leaks counted as losses; the mean over 500 Hz-2 kHz. Two like
          rooms joined by a doorway of area S fill in 2 V / (c S); a dead room beside a live one in about its own
          energy time constant. Energy that reaches l through another room fills it in the sum of the two steps'
          times where that is quicker (a chain of build-ups: their mean delays add), so rooms that share only a
          wall but each a door with a third fill through the third;
        * ``open`` (R,): :meth:`open_share`; ``gen``: a number no other split in this process has."""
        if self._split_now is not None and self._split_version == self.scene.dynamic_version:  # no door moved
            return self._split_now
        self._split_version = self.scene.dynamic_version
        key = tuple(np.round(self.graph.apertures(), 4))
        if key in self._split:  # a door state met before (a door shut and opened again)
            self._split_now = self._split[key]
            remember(self._split, key, self._split_now)
            return self._split_now
        K = self.coupling()
        c = 343.0
        M = self._balance(K)  # (9, R, R), every band at once
        energy = np.ascontiguousarray(16 * np.pi * np.linalg.inv(M).transpose(2, 1, 0))  # [s, l, band]
        sq = np.sqrt(self.V)
        lam, U = np.linalg.eigh((c / 4) * M / np.outer(sq, sq))  # symmetric: V^-1/2 M V^-1/2; (9, R), (9, R, R)
        lam = np.maximum(lam, 1e-9)
        # E_l(t) after a unit impulse in room s: sum_k U_lk U_sk / sqrt(V_l V_s) exp(-lam_k t)
        w = U[:, :, None, :] * U[:, None, :, :] / lam[:, None, None, :]  # [band, l, s, k] time integrals
        tot = w.sum(3)
        share = np.clip(np.where(tot[..., None] > 0, w / np.where(tot > 0, tot, 1.0)[..., None], 0.0), 0.0, 1.0)
        modes_share = np.ascontiguousarray(share.transpose(3, 2, 1, 0))  # [k, s, l, band]
        modes_rt = np.ascontiguousarray((13.8155 / lam).T)  # (R, 9)
        slow, slow_rt = modes_share[0], modes_rt[0]
        own_rt = np.ascontiguousarray((13.8155 / ((c / 4) * np.diagonal(M, axis1=1, axis2=2) / self.V)).T)
        U0 = U[5]
        _SPLITS[0] += 1
        out = {"buildup_tau": self._buildup_tau(K, c), "energy": energy, "slow": slow, "slow_rt": slow_rt,
               "own_rt": own_rt,
               "slow_room": int(np.argmax(U0[:, 0] ** 2)), "modes_rt": modes_rt, "modes_share": modes_share,
               "modes_room": np.argmax(U0 ** 2, axis=0), "open": self.open_share(), "gen": _SPLITS[0]}
        remember(self._split, key, out)
        self._split_now = out
        return out

    def _buildup_tau(self, K: np.ndarray, c: float) -> np.ndarray:
        """``late_split``'s ``buildup_tau`` from the couplings K (R, R, 9) and the speed of sound ``c``."""
        R = len(self.rooms)
        tau = np.zeros((R, R))
        mid = [int(np.argmin(np.abs(BANDS - f))) for f in (500.0, 1000.0, 2000.0)]
        for b in mid:
            loss = (c / 4) * (self.A[:, b] + K[:, :, b].sum(1)) / self.V  # each room's decay rate, its leaks counted
            x = (c / 4) * K[:, :, b] / np.sqrt(np.outer(self.V, self.V))  # the symmetric exchange between two rooms
            # the two eigenvalues of [[a, -x], [-x, d]] differ by sqrt((a - d)^2 + 4 x^2)
            gap = np.sqrt((loss[:, None] - loss[None, :]) ** 2 + 4 * x ** 2)
            tau += 1.0 / np.maximum(gap, 1e-9) / len(mid)
        np.fill_diagonal(tau, 0.0)
        for m in range(R):  # through room m, where quicker (Floyd-Warshall)
            np.minimum(tau, tau[:, m:m + 1] + tau[m:m + 1, :], out=tau)
        return tau

    def room_of(self, xy: np.ndarray) -> np.ndarray:
        """(n,) room index of points (n, 2) (the room of the slice's cell they are in), -1 outside every room."""
        g = self.graph
        ij = np.floor((np.asarray(xy, float)[:, ::-1] - g.origin[::-1]) / g.cell).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < np.array(g.shape)), axis=1)
        out = np.full(len(ij), -1)
        out[inside] = self.labels[ij[inside, 0], ij[inside, 1]]
        return out


_CACHE: dict = {}


def room_coupling(scene, graph, probes) -> RoomCoupling:
    """The scene's :class:`RoomCoupling`, built once per structure, rooms and probes (8 kept; an env builds a
    renderer per episode) and bound to this scene's doors."""
    import copy

    key = (scene.static_hash(), tuple((r.name, r.footprint.tobytes()) for r in scene.rooms),
           tuple(np.round(np.r_[p.position, p.rt60], 4).tobytes() for p in probes or []))
    c = _CACHE.get(key)
    if c is None:
        c = RoomCoupling(scene, graph, probes)
        _CACHE[key] = c
        while len(_CACHE) > 8:
            _CACHE.pop(next(iter(_CACHE)))
    if c.scene is not scene or c.graph is not graph:
        c = copy.copy(c)
        c.scene, c.graph, c._cache, c._rc = scene, graph, {}, None
        c._version, c._split, c._split_version = None, {}, None
        c.rooms = list(scene.rooms)  # the same rooms (the key), this scene's objects
    return c
