"""The late reverb's per-block work, mixed into :class:`~sonicverse_core.acoustics.renderer.AcousticRenderer`
(the renderer's module docstring says what it does): the sends of every source to the listener's reverb, the
probes' tails around the listener, the rooms' coupling per band, and with probes baked per room the two coupled
tails (the listener's room's own decay and the slowest mode's)."""
from __future__ import annotations

import math

import numpy as np

from sonicverse_core.acoustics.kernels import (farther, groups_sending, late_groups, late_send, mix_ramped,
                                               portal_curve, rows_moved)
from sonicverse_core.acoustics.probes import SPEED_OF_SOUND
from sonicverse_core.scene.materials import BANDS

MID = slice(4, 7)  # 500 Hz - 2 kHz
MAX_MIXING_TIME = 0.08  # s: the late tail starts at most this long after the direct sound
SLOW_SEED = 1000  # the slowest coupled mode's tails: noise independent of the rooms' own
PORTAL_STEP = 5.0  # degrees: the azimuth table of the neighbouring room's direction


class LateReverb:
    """Methods of the renderer; they use its probes, coupling, source ring and per-listener state."""

    def _late(self, st, lis, dist, occ, out) -> None:
        """The late reverb of every source, added into ``out``."""
        cfg, n, B = self.cfg, self._n, self.cfg.block
        key = st.get("late_key")
        if key is None or farther(key, lis.position, 0.01):  # probe interpolation, per centimetre moved
            w = 1 / np.maximum(np.linalg.norm(self._probe_pos - lis.position, axis=1), 0.1) ** 2
            if self.coupling is not None:  # the listener's own room's probes (its neighbours come by coupling)
                st["lis_room"] = int(self.coupling.room_of(lis.position[None, :2])[0])
                if st["lis_room"] >= 0:
                    if getattr(self, "_probe_room", None) is None:
                        self._probe_room = self.coupling.room_of(self._probe_pos[:, :2])
                    mine = self._probe_room == st["lis_room"]
                    if mine.any():
                        w = np.where(mine, w, 0.0)
            if len(w) > 2:  # the two nearest probes: each one mixed in costs a convolution per block
                w[np.argsort(w)[:-2]] = 0.0
            w /= w.sum()
            rt = w @ self._probe_rt
            vol = float(w @ self._probe_vol)
            if self.coupling is not None and st["lis_room"] >= 0 and self.coupling.rooms[st["lis_room"]].volume > 1:
                vol = self.coupling.rooms[st["lis_room"]].volume  # the room's own (a proxy box sees through doors)
            lo, hi = float(np.mean(rt[3:6])), float(rt[7])  # 250 Hz-1 kHz and 4 kHz: the FDN's two fit points
            # diffuse-field level relative to the direct sound at 1 m: 16 pi / A, A = 0.161 V / T (Sabine)
            level = np.sqrt(16 * np.pi * max(lo, 0.05) / (0.161 * max(vol, 1.0)))
            t_mix = float(np.clip(np.sqrt(max(vol, 0.0)) / 1000.0, 0.005, MAX_MIXING_TIME))  # Polack: sqrt(V) ms
            st["late_key"], st["late_params"] = lis.position.copy(), (w, lo, hi, level, t_mix)
            st["room_reverbs"] = int(np.count_nonzero(w > 1e-4))  # tails convolved for this listener
            st["late_gen"] = st.get("late_gen", 0) + 1  # the listener moved: the modal mix is made again
        w, lo, hi, level, t_mix = st["late_params"]
        if self._modal and st.get("lis_room", -1) >= 0:
            self._late_modal(st, lis, dist, occ, w, lo, t_mix, out)
            return
        # Barron & Lee 1988: the late level falls with source distance; a source behind walls excites the
        # coupled space: the send keeps the square root of the direct path's mid-band transmission
        group, use_occ, shapes = self._late_groups(st, n)
        self.stats["room_reverbs"] = st["room_reverbs"]
        sends = st["sends"]
        late_send(self._ring, (self.write - B) % self.hist, dist, occ, use_occ, group, lo, st["send"][:n],
                  st["send_delay"][:n], st["fresh"][:n], sends, float(cfg.sample_rate), SPEED_OF_SOUND, t_mix)
        self.stats["rooms_sending"] = groups_sending(group, st["send"][:n], st["seen"])
        lv0 = st["late_level"] if st["late_level"] is not None else level
        st["late_level"] = level
        if "fdn" in st:
            old = st.get("fdn_rt")
            if old is None or abs(old[0] - lo) > 0.002 * lo or abs(old[1] - hi) > 0.002 * hi:  # 0.2 %
                st["fdn"].set_rt60(lo, hi)
                st["fdn_rt"] = (lo, hi)
            np.matmul(st["mid"], sends, out=st["mono"])  # the groups' mid-band couplings
            add = st["fdn"].process(st["mono"], out=st["fdn_out"])
            mix_ramped(add, 1.0, 1.0, lv0, level, 1.0, out)
            return
        if len(w) < len(self._tail_rt):  # the shut-door tails play no part outside the rooms
            w = np.r_[w, np.zeros(len(self._tail_rt) - len(w))]
            st["late_params"] = (w, lo, hi, level, t_mix)
        st["conv"].process(sends, w, shapes, out=out, level=(lv0, level), shapes_key=st["shapes_key"])

    def _late_modal(self, st, lis, dist, occ, w, lo, t_mix, out) -> None:
        """The late reverb of coupled rooms (``coupling.late_split``): each source room's send, shaped per band,
        feeds the listener's own room's decay (its probes' tails, blended between doors open and shut as the room's
        decay with its doors as they are) and the slowest mode's (the tails of the room it rings in); the energies
        are the rooms' statistical energy balance, no Sabine level."""
        n, B = self._n, self.cfg.block
        c, lr = self.coupling, st["lis_room"]
        group, use_occ, _ = self._late_groups(st, n)
        split = c.late_split()
        key = (split["gen"], st["late_gen"])
        if st.get("modal_key") != key:
            st["modal_w"], st["modal_shapes"] = self._modal_mix(st, lis, w, split, lr)
            st["modal_key"] = key
            st["room_reverbs"] = int(np.count_nonzero(st["modal_w"][0] > 1e-4) +
                                     np.count_nonzero(st["modal_w"][1] > 1e-4))
        self.stats["room_reverbs"] = st["room_reverbs"]
        sends = st["sends"]
        late_send(self._ring, (self.write - B) % self.hist, dist, occ, use_occ, group, lo, st["send"][:n],
                  st["send_delay"][:n], st["fresh"][:n], sends, float(self.cfg.sample_rate), SPEED_OF_SOUND, t_mix)
        self.stats["rooms_sending"] = groups_sending(group, st["send"][:n], st["seen"])
        (w_own, w_slow), (sh_own, sh_slow) = st["modal_w"], st["modal_shapes"]
        st["conv"].process(sends, w_own, sh_own, out=out, shapes_key=key)
        st["conv_slow"].process(sends, w_slow, sh_slow, out=out, shapes_key=key, ears=self._portal_ears(st, lis))

    def _portal_ears(self, st, lis):
        """The slow tail's per-ear gains when it rings in another room: the level differences of the direction it
        enters from (the doorway, ``_modal_mix``), for the head as it is turned now (a table row per 5 degrees of
        azimuth; the gains are made again only when the row changes: nothing allocated while the head turns)."""
        portal = st["portal"]
        if portal is None:
            return None
        (px, py), beta = portal
        p = lis.position
        az = math.degrees(math.atan2(py - p[1], px - p[0])) - lis.yaw
        idx = int(round(az / PORTAL_STEP)) % len(self._portal_table)
        if idx != st["portal_idx"]:
            portal_curve(self._portal_table[idx], beta, self._portal_bins, st["ears"])
            st["portal_idx"] = idx
        return st["ears"]

    def _portal_tables(self):
        """(A, 2, 9) per-band ear gains of azimuths k x 5 degrees in the horizontal plane over the diffuse field's,
        normalised to a mean power of 1 over the two ears (binaural: the HRTF set; stereo: the constant-power
        panner), and (9, block + 1) the bands' weights over the convolution's bins; None for mono output."""
        if getattr(self, "_portal_table", None) is not None or self.cfg.output == "mono":
            return
        az = np.radians(np.arange(0.0, 360.0, PORTAL_STEP))
        if self.hrtf is not None:
            n = 1 << int(np.ceil(np.log2(max(4096, 2 * self.hrtf.taps))))
            H, _ = self.hrtf.lookup_spectra(np.c_[np.cos(az), np.sin(az), np.zeros(len(az))], n)
            f = np.fft.rfftfreq(n, 1 / self.cfg.sample_rate)
            diffuse = self.hrtf.diffuse_field[0]
            ratio = np.ones((len(az), 2, len(BANDS)))
            for b, fc in enumerate(BANDS):
                sel = (f >= fc / np.sqrt(2)) & (f < fc * np.sqrt(2))
                if sel.any():
                    ratio[:, :, b] = np.sqrt(np.mean(np.abs(H[:, :, sel]) ** 2, axis=2)) / diffuse[None, :, b]
        else:  # the stereo panner: constant power by the lateral component (left ear towards +y)
            s = np.sin(az)
            ratio = np.repeat(np.stack([np.sqrt(1 + s), np.sqrt(np.maximum(1 - s, 0.0))], 1)[:, :, None],
                              len(BANDS), axis=2)
        ratio /= np.sqrt(np.mean(ratio ** 2, axis=1, keepdims=True))
        self._portal_table = ratio
        fb = np.fft.rfftfreq(2 * self.cfg.block, 1 / self.cfg.sample_rate)
        lf = np.log2(np.maximum(fb, BANDS[0]))
        self._portal_bins = np.stack([np.interp(lf, np.log2(BANDS), e) for e in np.eye(len(BANDS))])

    def _portal(self, lis, split, lr):
        """Where the slow mode's room is heard from when it is not the listener's: the last bend of the open path
        from its probe (the doorway), the probe itself in sight or through a wall; and the share of that room's
        energy arriving straight from there rather than diffused in the listener's room: x / (1 + x),
        x = D / (4 pi r^2), D the listener's room's absorption plus its couplings at 1 kHz, r the distance (an
        aperture of the coupling's area radiating the neighbour's diffuse field). None for the listener's own
        room or mono output."""
        room = split["slow_room"]
        if room == lr or self.cfg.output == "mono":
            return None
        self._portal_tables()
        c = self.coupling
        mine = np.flatnonzero(self._probe_room == room)
        if len(mine) == 0:
            return None
        xy = lis.position[:2]
        src = self._probe_pos[mine[np.argmin(np.sum((self._probe_pos[mine, :2] - xy) ** 2, axis=1))], :2]
        res = c.graph.path(src, xy)
        pt = res.last if res is not None else src
        r = max(float(np.hypot(*(pt - xy))), 0.5)
        D = c.A[lr, 5] + c.coupling()[lr, :, 5].sum()
        x = D / (4 * np.pi * r * r)
        return (float(pt[0]), float(pt[1])), x / (1 + x)

    def _modal_mix(self, st, lis, w, split, lr):
        """Tail weights (own, slow) over ``self._tail_rt`` and per-group per-band amplitudes (own, slow) (G, 9)."""
        P = len(self.probes)
        rt = self._tail_rt

        def blend(room, rt_now, weights):
            """Amplitude weights over the tails for ``room``'s probes (energy ``weights``), blended between doors
            open and shut so that the mid-band RT is ``rt_now``; and the blend's energy per band re the tails'
            normalisation (each tail carries rt_b / rt_mid of a flat one)."""
            mine = np.flatnonzero(self._probe_room == room)
            if len(mine) == 0:
                mine = np.array([int(np.argmax(weights))])
            p = weights[mine] if weights[mine].sum() > 0 else np.ones(len(mine))
            p = p / p.sum()
            shut = self._shut[mine]
            o, s_ = rt[mine].T @ p, rt[shut].T @ p  # (9,) room-mean open and shut RTs
            span = s_[MID].mean() - o[MID].mean()  # a room without openings: no shut-door tail of its own
            beta = float(np.clip((rt_now[MID].mean() - o[MID].mean()) / span, 0.0, 1.0)) \
                if span > 0.01 * o[MID].mean() else 0.0
            out = np.zeros(len(rt))
            out[mine] = np.sqrt(p * (1 - beta))
            out[shut] += np.sqrt(p * beta)
            e = (1 - beta) * o / o[MID].mean() + beta * s_ / s_[MID].mean()
            return out, e

        d2 = np.sum((self._probe_pos - lis.position) ** 2, axis=1)
        near = 1 / np.maximum(d2, 0.01)
        w_own, e_own = blend(lr, split["own_rt"][lr], np.asarray(w[:P], float) ** 2)
        w_slow, e_slow = blend(split["slow_room"], split["slow_rt"], near)
        E, f = split["energy"][:, lr], split["slow"][:, lr]  # (R_s, 9)
        own = np.sqrt(np.maximum(E * (1 - f), 0.0) / np.maximum(e_own, 1e-9))
        slow = np.sqrt(np.maximum(E * f, 0.0) / np.maximum(e_slow, 1e-9))
        sh_own, sh_slow = np.empty((self._groups, len(BANDS))), np.empty((self._groups, len(BANDS)))
        sh_own[0], sh_own[1:] = own[lr], own
        sh_slow[0], sh_slow[1:] = slow[lr], slow
        st["portal"], st["portal_idx"] = self._portal(lis, split, lr), -1
        return (w_own, w_slow), (sh_own, sh_slow)

    def _late_groups(self, st, n: int):
        """Per source, which send it joins (0: the listener's room, or rooms unknown; 1 + r: room r, filtered by
        its coupling to the listener's room) and whether its send falls with the direct path's transmission (rooms
        unknown); the groups' per-band amplitudes (G, 9), rewritten (and ``st["shapes_key"]`` changed) only when
        the listener's room or the coupling changes."""
        group, use_occ = st["group"][:n], st["use_occ"][:n]
        lr = st.get("lis_room", -1)
        if self.coupling is None or lr < 0:
            group.fill(0)
            use_occ.fill(True)
            if st["shapes_key"] != -1:
                st["shapes"][:] = 1.0
                st["shapes_key"] = -1
                if "mid" in st:
                    st["mid"][:] = 1.0
            return group, use_occ, st["shapes"]
        c, pos = self.coupling, self._pos[:n]
        moved = st["group_moved"] if "group_moved" in st and len(st["group_moved"]) >= n else None
        if moved is None:
            moved = st["group_moved"] = np.zeros(self._cap, bool)
        if rows_moved(self._src_room_at[:n], pos, 0.05, moved[:n]):
            idx = np.flatnonzero(moved[:n])
            self._src_room[idx] = c.room_of(pos[idx, :2])
            self._src_room_at[idx] = pos[idx]
        late_groups(self._src_room[:n], lr, group, use_occ)
        key = (c.scene.dynamic_version, lr)  # the transfer changes with the doors only
        if st["shapes_key"] != key:
            st["shapes"][1:] = c.transfer()[:, lr]  # the reverb transforms only the groups with sound
            st["shapes"][0] = 1.0
            st["shapes_key"] = key
            if "mid" in st:
                st["mid"][:] = st["shapes"][:, MID].mean(1)
        return group, use_occ, st["shapes"]
