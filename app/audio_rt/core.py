"""The audio side: the renderer for the user's ears and the robots', and the body of the stream callback.

The callback (:meth:`AudioCore.callback`) does, per block: copy the microphone into its ring; read the newest pose
frame through the sequence lock and advance the interpolated poses; move the listeners, the sources, the mouth
(the microphone's source) and the doors; render one block; write the user's block to the output and every
listener's block to its ring; record its own duration. Its state (rings, pose and output buffers, the renderer's
per-source and per-listener arrays, FFT plans, the listeners' output blocks) is allocated before the stream starts;
in steady state (nothing moved beyond the occlusion tolerance, no door moving) a callback allocates no array memory
and numba none (tests/test_poison.py counts both).
An exception is caught, counted and written to the error slot, and the block plays silence.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from app.audio_rt import config as C
from app.audio_rt.config import AudioConfig, AudioScene
from app.audio_rt.poses import PoseInterpolator, PoseLayout, mouth
from app.audio_rt.sched import NICE_CALLBACK, favour_if_time_shared
from app.audio_rt.shared import Layout, Ring, SeqLock
from sonicverse_core.acoustics.kernels import all_finite, farther

ERROR_BYTES = 1024


def burst_period(sample_rate: int, block: int) -> int:
    """Frames between the loopback test's noise bursts: half a second, whole blocks."""
    return int(0.5 * sample_rate) // block * block


def shared_layout(cfg: AudioConfig, n_listeners: int, pose: PoseLayout) -> Layout:
    cap = int(cfg.ring_seconds * cfg.sample_rate)
    L = Layout()
    L.add("tele", C.N_TELE, np.int64)
    L.add("telef", C.N_TELEF, np.float64)
    L.add("dur", (2, C.DURATIONS), np.float32)  # each callback's wall time, then its thread's CPU time (s)
    L.add("dur_head", 1, np.int64)
    L.add("xrun_at", C.XRUN_LOG, np.int64)
    L.add("error", ERROR_BYTES, np.uint8)
    L.add("pose_seq", 1, np.int64)
    L.add("pose", pose.size, np.float64)
    L.add("mic", (1, cap), np.float32)
    L.add("mic_head", 1, np.int64)
    for k in range(n_listeners):  # 0: the user's ears (what was sent to the output), 1..: robots
        L.add(f"ears{k}", (2, cap), np.float32)
        L.add(f"ears{k}_head", 1, np.int64)
    return L


def attach(cfg: AudioConfig, scene_setup: AudioScene, buf=None, shm_path: str | None = None):
    """(Shared, PoseLayout): a worker's view of the engine's shared block, the layout derived from the same
    settings as the engine's; ``buf`` (thread mode) or the block mapped from ``shm_path``."""
    from app.audio_rt.shared import SharedBlock

    pose_layout = PoseLayout(len(scene_setup.robots), len(scene_setup.sources), len(scene_setup.doors))
    n_listeners = 1 + len(scene_setup.robots)
    layout = shared_layout(cfg, n_listeners, pose_layout)
    if buf is None:
        buf = SharedBlock(layout.size, shm_path, create=False).buf
    return Shared(layout, buf, n_listeners), pose_layout


class Shared:
    """Both sides' view of the block: rings, the pose seqlock, telemetry and the error slot."""

    def __init__(self, layout: Layout, buf, n_listeners: int):
        v = layout.views(buf)
        self.v = v
        self.tele, self.telef, self.error = v["tele"], v["telef"], v["error"]
        self.xrun_at = v["xrun_at"]  # callback index of xrun k at [k % XRUN_LOG]; k counts up to tele[XRUNS]
        self.durations = Ring(v["dur"], v["dur_head"])
        self.poses = SeqLock(v["pose_seq"], v["pose"])
        self.mic = Ring(v["mic"], v["mic_head"])
        self.ears = [Ring(v[f"ears{k}"], v[f"ears{k}_head"]) for k in range(n_listeners)]

    def set_error(self, message: str) -> None:
        b = message.encode("utf-8", "replace")[: ERROR_BYTES - 1]
        self.error[: len(b)] = np.frombuffer(b, np.uint8)
        self.error[len(b)] = 0
        self.tele[C.ERROR_SEQ] += 1

    def error_text(self) -> str:
        raw = bytes(self.error)
        return raw[: raw.index(0) if 0 in raw else len(raw)].decode("utf-8", "replace")


def build_renderer(scene_setup: AudioScene, cfg: AudioConfig, scene=None, role: str = "all"):
    """(renderer, scene, mic source or None, user listener or None, door names) for the audio side; ``scene``: an
    already loaded core scene to render (shared with the caller, e.g. the headless VR loop), else
    ``scene_setup.spec`` is loaded. ``role``: which listeners it renders: 'all' (the user first, then the robots),
    'user' (the stream's callback when robots render in their own process) or 'robots'."""
    from assets_manifest.soundbank import load_sound
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    probes = None
    if scene is None and scene_setup.spec is not None:
        from sonicverse_core.scene.spec import load_scene

        scene = load_scene(scene_setup.spec)
    if scene is not None:
        if scene_setup.late_reverb or scene_setup.early_reflections:
            from sonicverse_core.acoustics.probes import BakeConfig, scene_probes

            probes = scene_probes(scene, BakeConfig(rays=scene_setup.bake_rays))
    rc = RenderConfig(sample_rate=cfg.sample_rate, block=cfg.block, occlusion=scene_setup.occlusion,
                      output="binaural" if scene_setup.hrtf else "stereo",
                      early_reflections=scene_setup.early_reflections, late_reverb=scene_setup.late_reverb,
                      occlusion_rays_per_block=scene_setup.occlusion_budget)
    r = AcousticRenderer(scene, rc, probes=probes)
    for s in scene_setup.sources:
        if isinstance(s.sound, str):
            sig, sr = load_sound(s.sound)
        else:
            sig, sr = np.asarray(s.sound, np.float32), s.sample_rate or cfg.sample_rate
        r.add_source(sig, s.position, loop=s.loop, gain=s.gain, sample_rate=sr)
    mic = None
    head = np.array(scene_setup.head, float)
    if cfg.mic:
        m, fwd = mouth(head)
        mic = r.add_source(live=True, position=m, gain=cfg.mic_gain, directivity=scene_setup.mic_directivity,
                           forward=fwd)
    user = None
    if role != "robots":
        user = r.add_listener(head[:3], head[3], head[4],
                              exclude=[mic] if mic is not None and not cfg.sidetone else ())
    for rb in scene_setup.robots if role != "user" else ():
        r.add_listener(rb[:3], rb[3])
    doors = [d.name for d in scene.doors] if scene is not None else []
    return r, scene, mic, user, doors


class AudioCore:
    """Owns the renderer on the audio side and implements the stream callback."""

    def __init__(self, cfg: AudioConfig, scene_setup: AudioScene, shared: Shared, pose_layout: PoseLayout,
                 renderer=None, role: str = "all"):
        self.cfg, self.sh, self.L = cfg, shared, pose_layout
        if renderer is None:
            renderer = build_renderer(scene_setup, cfg, role=role)
        self.r, self.scene, self.mic, self.user, self.doors = renderer
        self.n_scene = len(scene_setup.sources)
        self.robots = [lis for lis in self.r.listeners if lis is not self.user]
        B = cfg.block
        self.block_s = B / cfg.sample_rate
        self.interp = PoseInterpolator(pose_layout)
        self.frame = np.zeros(pose_layout.size)
        head = np.array(scene_setup.head, float)
        self.interp.new_frame(pose_layout.frame(
            0.0, head, robots=[rb for rb in scene_setup.robots],
            sources=[s.position for s in scene_setup.sources], gains=[s.gain for s in scene_setup.sources],
            doors=[self.scene.object(d).open_fraction for d in self.doors] if self.doors else (),
            sidetone=cfg.sidetone))
        self.door_state = self.interp.cur[pose_layout.DOORS].copy()
        self.door_change = False
        self.sidetone = cfg.sidetone
        self.mic_block = np.zeros(B, np.float32)
        self.zero_in = np.zeros((B, 1), np.float32)  # the "microphone" of an output-only stream
        self.out_block = np.zeros((2, B), np.float32)
        self.outs = [np.zeros((2, B), np.float32) for _ in self.r.listeners]  # the renderer writes into these
        # loopback test signal: a 4096-sample white-noise burst every half second on the left channel
        self.test = None
        if cfg.test_signal:
            rng = np.random.default_rng(1234)
            self.test = np.zeros(burst_period(cfg.sample_rate, B), np.float32)
            self.test[:4096] = 0.25 * rng.uniform(-1, 1, 4096).astype(np.float32)
        self.frames = 0
        self.warmup_blocks = scene_setup.warmup_blocks
        self._dur = np.zeros((2, 1), np.float32)

    def warm_up(self) -> None:
        """Render the first blocks before the stream starts: JIT caches load, every occlusion ray is cast once.
        The kernels that only run once the stream does (a microphone block, a pose ramp, a door check) are called
        here too: compiled in the callback they would cost seconds, and two workers compiling the same kernel at the
        same moment race on numba's cache files. First the renderer visits every probe and moves every door
        (:meth:`AcousticRenderer.warm_kernels`): a kernel that only runs in another room (its walls' images, a path
        round a corner) compiled in the callback stalled it for seconds on a fresh install, and the stream was lost."""
        from sonicverse_core.acoustics.kernels import lerp, scale_into

        self.r.warm_kernels()
        for _ in range(self.warmup_blocks):
            if self.mic is not None:
                self.mic.pending = self.mic_block  # silence, through the live path
            self._apply_poses()
            self.r.render_block(self.outs)
        scratch = np.zeros_like(self.interp.cur)
        lerp(self.interp.cur, self.interp.cur, 1.0, scratch)
        scale_into(self.mic_block, 1.0, np.zeros_like(self.mic_block))
        farther(self.door_state, self.door_state, 0.0)
        all_finite(self.mic_block)

    def _apply_poses(self) -> None:
        L, sh = self.L, self.sh
        got = sh.poses.read_into(self.frame)
        if got == 1:
            self.interp.new_frame(self.frame)
            sh.tele[C.POSE_FRAMES] += 1
        elif got < 0:
            sh.tele[C.POSE_TORN] += 1
        v = self.interp.advance(self.block_s)
        r = self.r
        head = v[L.HEAD]
        if self.user is not None:
            r.set_listener(self.user, head[:3], head[3], head[4])
        for k, lis in enumerate(self.robots):
            rb = v[L.ROBOTS.start + 4 * k: L.ROBOTS.start + 4 * k + 4]
            r.set_listener(lis, rb[:3], rb[3], 0.0)
        n = self.n_scene
        if n:
            r._pos[:n] = v[L.SOURCES].reshape(n, 3)
            r._gain[:n] = v[L.GAINS]
        if self.mic is not None:
            mouth(head, out=(r._pos[self.mic.index], r._fwd[self.mic.index]))
            side = float(v[L.SIDETONE])
            if (side > 0) != (self.sidetone > 0) and self.user is not None:
                r.set_heard(self.user, self.mic, side > 0)
            self.sidetone = side
        if self.doors:  # doors take the newest frame's state, not a ramp: one geometry rebuild per change
            if farther(self.interp.target[L.DOORS], self.door_state, 0.0):
                self.door_change = True

    def _apply_doors(self) -> None:
        """After a block's output is written: move the doors and build their geometry (``set_doors``); the blocks
        after it render the move, a part each (a door's cost is spread over the callbacks)."""
        d = self.interp.target[self.L.DOORS]
        moved = np.flatnonzero(d != self.door_state)
        self.r.set_doors({self.doors[k]: d[k] for k in moved})
        self.door_state[moved] = d[moved]
        self.door_change = False

    def render_robots(self, mic_block: np.ndarray | None) -> None:
        """One block for the robot listeners only (role 'robots': their own process, paced by the callback's
        microphone ring): their ears go to rings 1.. exactly as when the callback renders them."""
        if self.mic is not None:
            self.mic.pending = mic_block
        self._apply_poses()
        outs = self.r.render_block(self.outs)
        for k, o in enumerate(outs):
            self.sh.ears[1 + k].write(o)
        if self.door_change:
            self._apply_doors()

    def callback(self, indata, outdata, frames, time_info, status) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        sh, tele = self.sh, self.sh.tele
        mic_written = False
        try:
            if status:
                sh.xrun_at[tele[C.XRUNS] % C.XRUN_LOG] = tele[C.CALLBACKS]
                tele[C.XRUNS] += 1
                if status.input_overflow:
                    tele[C.IN_OVERFLOW] += 1
                if status.output_underflow:
                    tele[C.OUT_UNDERFLOW] += 1
                if status.priming_output:
                    tele[C.PRIMING] += 1
            if tele[C.CB_POLICY] < 0:  # once: the scheduling the audio server gave this thread (telemetry's news),
                # raised to nice -20 where the server's is time-shared (a machine that refuses it real time)
                policy, tele[C.CB_PRIORITY], tele[C.CB_NICE] = favour_if_time_shared(NICE_CALLBACK)
                tele[C.CB_TID] = threading.get_native_id()
                tele[C.CB_POLICY] = policy
            if frames != self.cfg.block:
                raise RuntimeError(f"the device delivered {frames} frames, not {self.cfg.block}")
            if tele[C.FAULTS] > 0:  # test hook: the main side asks for a failing block
                tele[C.FAULTS] -= 1
                raise RuntimeError("injected fault (test hook)")
            if self.mic is not None:
                mb = self.mic_block
                mb[:] = indata[:, self.cfg.mic_channel]
                if not all_finite(mb):  # a NaN/inf sample (a broken driver): zeros, counted
                    np.nan_to_num(mb, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
                    np.clip(mb, -1e6, 1e6, out=mb)
                    tele[C.MIC_NONFINITE] += 1
                sh.mic.write(mb[None])
                mic_written = True
                self.mic.pending = self.mic_block
            self._apply_poses()
            outs = self.r.render_block(self.outs)
            ob = self.out_block
            ob[:] = outs[0]
            if self.test is not None:
                i = self.frames % len(self.test)
                ob[0] += self.test[i:i + frames]
                np.clip(ob, -1.0, 1.0, out=ob)
            outdata[:, 0] = ob[0]
            outdata[:, 1] = ob[1]
            if outdata.shape[1] > 2:
                outdata[:, 2:] = 0.0
            sh.ears[0].write(ob)
            for k in range(1, len(outs)):
                sh.ears[k].write(outs[k])
            if self.door_change:
                self._apply_doors()
            tele[C.RECOVERIES] = self.r.stats["recoveries"]
        except Exception as exc:  # noqa: BLE001 - the callback must never raise into PortAudio
            outdata.fill(0.0)
            if self.mic is not None and not mic_written:  # the mic ring stays in step with the frame counter
                sh.mic.write(self.zero_in[:, :1].T)
            try:  # the message first, then the count the engine polls: it never reads a count without its text
                sh.set_error(f"{type(exc).__name__}: {exc}")
            except Exception:  # noqa: BLE001
                pass
            tele[C.ERRORS] += 1
        self.frames += frames
        tele[C.FRAMES] = self.frames
        tele[C.CALLBACKS] += 1
        t1 = time.perf_counter()
        sh.telef[C.LAST_CALLBACK] = t1
        self._dur[0, 0] = t1 - t0
        self._dur[1, 0] = time.thread_time() - c0  # far below the wall time: the thread was held off its CPU
        sh.durations.write(self._dur)
