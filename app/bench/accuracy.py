"""`sonicverse bench accuracy`: every knob that trades accuracy for speed, error against a reference vs run time.

Knobs and references:
* rays per probe, bounces: per-band RT60 of a diffuse shoebox vs Eyring (bands with absorption <= 0.15, where
  Eyring holds), and vs a bake with ``reference_rays`` in the apartment's living room; time per probe.
* scattering model (stochastic vs vector-based): per-band RT60 (250 Hz-4 kHz) of a uniform plaster shoebox vs
  Eyring, and the rendered T30 under an absorbing ceiling vs pyroomacoustics (whose tracer scatters by vectors);
  time per probe.
* late model (probes baked over the whole connected space vs per room, coupled): strength G against
  pyroomacoustics in the dead-room and two-room cases of ``bench fidelity``; render time of 3 s.
* probes per scene: RT60 interpolated at random listener points vs a probe baked at that very point; bake time.
* HRTF interpolation and filter length: leave-one-out over measured KEMAR directions (interpolate a held-out
  direction from the others, log-spectral distance 200 Hz-16 kHz to the measurement); time per 64 lookups.
* early reflections: echogram (1 ms energy bins, first 60 ms) of the engine's direct + image sources vs
  pyroomacoustics' image-source RIR of the same shoebox; render time per block.
* reverb method (FDN vs partitioned convolution): per-band RT60 measured on the rendered tail vs the probe's;
  time per block.
* block size: a source moving at 2 m/s rendered at each block size vs block 16 (relative RMS difference); time
  per second of audio.
* propagation paths' grid cell: path length and last-bend direction round the L-room's corner vs the exact
  geometry; time to bake the scene's path graph.
* the late re-mix's delay after a door's move (blocks): each block's binaural energy after the move vs the re-mix
  made at once; the costliest of the three blocks after a move.
"""
from __future__ import annotations

import contextlib
import time

import numpy as np


def _timed(fn, reps=1):
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn()
    return out, (time.perf_counter() - t0) / reps


def _pareto(points):
    """Indices of the non-dominated (error, time) points."""
    keep = []
    for i, (e, t) in enumerate(points):
        if not any((e2 <= e and t2 <= t) and (e2 < e or t2 < t) for j, (e2, t2) in enumerate(points) if j != i):
            keep.append(i)
    return keep


def _rays_and_bounces(reference_rays: int, quick: bool):
    from sonicverse_core.acoustics.probes import BakeConfig, bake, bake_probe, default_probe_positions, eyring_rt60
    from sonicverse_core.geometry.raycast import SceneRayCaster
    from sonicverse_core.scene.materials import get_material
    from sonicverse_core.scene.spec import load_scene

    box = load_scene("shoebox:6x4x3?material=BrickBare")
    ey = eyring_rt60((6, 4, 3), box.metadata["surface_materials"])
    diffuse = np.array(get_material("BrickBare").absorption) <= 0.15
    cbox = SceneRayCaster(box)
    apt = load_scene("builtin:apartment")
    living = next(r for r in apt.rooms if r.type == "living room")
    pos = default_probe_positions(apt)
    at = pos[np.argmin(np.linalg.norm(pos[:, :2] - living.footprint.mean(0), axis=1))]
    ref = bake(apt, at[None], BakeConfig(rays=reference_rays), progress=False)[0].rt60
    capt = SceneRayCaster(apt)
    rows = []
    for rays in ((500, 2000) if quick else (250, 500, 1000, 2000, 4000, 8000)):
        p, t = _timed(lambda: bake_probe(cbox, [2.3, 1.6, 1.4], BakeConfig(rays=rays, max_time=8.0)))
        q, t2 = _timed(lambda: bake_probe(capt, at, BakeConfig(rays=rays)))
        rows.append({"setting": rays, "error": float(np.mean(np.abs(p.rt60[diffuse] / ey[diffuse] - 1))),
                     "error_vs_reference_bake": float(np.max(np.abs(q.rt60[2:] / ref[2:] - 1))),
                     "time_s": t2, "time_shoebox_s": t})
    bounce_rows = []
    for nb in ((20, 400) if quick else (10, 20, 50, 100, 400)):
        p, t = _timed(lambda: bake_probe(cbox, [2.3, 1.6, 1.4], BakeConfig(max_bounces=nb, max_time=8.0)))
        bounce_rows.append({"setting": nb, "error": float(np.mean(np.abs(p.rt60[diffuse] / ey[diffuse] - 1))),
                            "time_s": t})
    return ({"knob": "rays_per_probe", "error_metric": "mean |RT60/Eyring - 1| (shoebox 6x4x3 BrickBare, bands "
             "alpha <= 0.15); error_vs_reference_bake: max over 125 Hz-8 kHz of |RT60/RT60_ref - 1| in the "
             f"apartment's living room, reference {reference_rays} rays; time: one apartment probe",
             "rows": rows},
            {"knob": "max_bounces", "error_metric": "mean |RT60/Eyring - 1| (same shoebox)", "rows": bounce_rows})


def _scattering(quick: bool):
    from app.bench.fidelity import SHOEBOXES, _ours, _pra_polygon, room_parameters
    from sonicverse_core.acoustics.probes import SCATTERING, BakeConfig, bake_probe, eyring_rt60
    from sonicverse_core.geometry.raycast import SceneRayCaster
    from sonicverse_core.scene.spec import load_scene

    mid = slice(3, 8)  # 250 Hz - 4 kHz
    box = load_scene("shoebox:8x6x3?walls=PlasterRough&floor=ParquetOnConcrete&ceiling=PlasterRough")
    ey = eyring_rt60((8, 6, 3), box.metadata["surface_materials"])[mid]
    cbox = SceneRayCaster(box)
    (L, W, H), walls, floor, ceiling = SHOEBOXES["shoebox large absorbing ceiling"]
    spec = f"shoebox:{L:g}x{W:g}x{H:g}?walls={walls}&floor={floor}&ceiling={ceiling}"
    src, lis = (0.3 * L, 0.35 * W, 1.2), (0.7 * L, 0.6 * W, 1.5)
    peer = np.array(room_parameters(_pra_polygon([(0, 0), (L, 0), (L, W), (0, W)], H, walls, floor, ceiling, src,
                                                 lis, 5000 if quick else 20_000))["T30"], float)
    rows = []
    for model in SCATTERING:
        p, t = _timed(lambda: bake_probe(cbox, [3.3, 2.6, 1.5], BakeConfig(scattering=model)))
        ours = np.array(room_parameters(_ours(spec, src, lis, 3.0, model)[0])["T30"], float)
        rows.append({"setting": model, "error": float(np.mean(np.abs(p.rt60[mid] / ey - 1))),
                     "error_vs_pyroomacoustics": float(np.mean(np.abs(ours / peer - 1))), "time_s": t})
    return {"knob": "scattering_model", "error_metric": "mean |RT60/Eyring - 1| over 250 Hz-4 kHz in a uniform "
            "8x6x3 m plaster shoebox; error_vs_pyroomacoustics: mean |T30/T30_peer - 1| rendered in the 12x9x4 m "
            "shoebox under an absorbing ceiling; time: one probe", "rows": rows}


def _late_model(quick: bool):
    from app.bench.fidelity import _cases, _ours, _pra_polygon, room_parameters

    todo = [c for c in _cases() if c[0].startswith(("two rooms, open door, no", "dead room"))]
    peers = [np.array(room_parameters(_pra_polygon(corners, H, *mats[:3], src, lis, 5000 if quick else 20_000, 0,
                                                   *mats[3:]))["G"])
             for _, _, corners, H, mats, src, lis, _ in todo]
    rows = []
    for per_room in (False, True):
        err, t = [], 0.0
        for (_, spec, _, _, _, src, lis, _), peer in zip(todo, peers):
            h, _, t_render = _ours(spec, src, lis, 3.0, per_room=per_room)
            err.append(np.abs(np.array(room_parameters(h)["G"]) - peer))
            t += t_render
        rows.append({"setting": "per room" if per_room else "whole space", "error": float(np.mean(err)),
                     "time_s": t / len(todo), "error_per_case_db": [round(float(e.mean()), 2) for e in err]})
    return {"knob": "late_model", "error_metric": "mean |G - G_peer| (dB, 250 Hz-4 kHz) over bench fidelity's "
            + ", ".join(c[0] for c in todo) + "; time: rendering 3 s at 16 kHz", "rows": rows}


def _neighbour_tails(quick: bool):
    """Coupled rooms heard apart besides the slowest mode (``RenderConfig.neighbour_tails``) in bench fidelity's dead
    hall between two live rooms: the east room's decay heard in the hall, against pyroomacoustics."""
    from app.bench.fidelity import _cases, _onset, _ours, _pra_polygon, PRA_DELAY, room_parameters

    _, spec, corners, H, mats, src, lis, _ = next(c for c in _cases() if c[0].startswith("dead hall"))
    t_dir = _onset(spec, src, lis)
    peer = room_parameters(_pra_polygon(corners, H, *mats[:3], src, lis, 5000 if quick else 20_000, 0, *mats[3:]),
                           t_dir=t_dir + PRA_DELAY)
    rows = []
    _ours(spec, src, lis, 0.5, neighbour_tails=1)  # warm: the kernels and the tails' partitions
    for n in (0, 1):
        h, _, t_render = _ours(spec, src, lis, 3.0, neighbour_tails=n)
        ours = room_parameters(h, t_dir=t_dir)
        rows.append({"setting": n, "error": float(np.mean(np.abs(np.array(ours["EDT"]) / np.array(peer["EDT"]) - 1))),
                     "time_s": t_render,
                     "C50_error_db": [round(a - b, 2) for a, b in zip(ours["C50"], peer["C50"])]})
    return {"knob": "neighbour_tails", "error_metric": "mean |EDT / EDT_peer - 1| (250 Hz-4 kHz) in bench fidelity's "
            "dead hall between two live rooms, the source in the east room (one realisation of each model); time: "
            "rendering 3 s at 16 kHz (a neighbour's tail costs one convolution per listener: bench audio "
            "--listener-room)", "rows": rows}


def _probes(quick: bool):
    from sonicverse_core.acoustics.probes import BakeConfig, bake, default_probe_positions
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("builtin:apartment")
    rng = np.random.default_rng(1)
    pts = NavGrid(scene).sample(rng, 6 if quick else 12)
    pts = np.c_[pts[:, :2], np.full(len(pts), 1.5)]
    truth = np.array([p.rt60 for p in bake(scene, pts, BakeConfig(), progress=False)])
    rows = []
    for n in ((1, 4) if quick else (1, 2, 4, 8, 16)):
        P = default_probe_positions(scene, n, rng=np.random.default_rng(0))
        t0 = time.perf_counter()
        probes = bake(scene, P, BakeConfig(), cache=False)
        t = time.perf_counter() - t0
        X = np.array([p.position for p in probes])
        R = np.array([p.rt60 for p in probes])
        w = 1 / np.maximum(np.linalg.norm(pts[:, None] - X[None], axis=2), 0.1) ** 2
        est = (w / w.sum(1, keepdims=True)) @ R
        rows.append({"setting": n, "error": float(np.mean(np.abs(est[:, 2:] / truth[:, 2:] - 1))), "time_s": t})
    return {"knob": "probes_per_scene", "error_metric": "mean |RT60_interpolated / RT60_baked_there - 1| over "
            "random listener points (125 Hz-8 kHz)", "rows": rows}


def _hrtf(quick: bool):
    from assets_manifest.hrtf import HrirSet, kemar
    from sonicverse_core.acoustics.hrtf import HrtfInterpolator

    full = kemar()
    rng = np.random.default_rng(0)
    # held-out directions away from the hull's open bottom
    el = np.degrees(np.arcsin(full.directions[:, 2]))
    cand = np.flatnonzero((el > -30) & (el < 70))
    held = rng.choice(cand, 12 if quick else 40, replace=False)
    keep = np.setdiff1d(np.arange(len(full.directions)), held)
    sub = HrirSet("loo", full.sample_rate, full.directions[keep], full.hrirs[keep])
    sr = 48000
    ref = HrtfInterpolator(full, sr, taps=512)
    nfft = 1024
    f = np.fft.rfftfreq(nfft, 1 / sr)
    band = (f > 200) & (f < 16000)
    rows = []
    dirs = full.directions[held]
    truth = np.abs(np.fft.rfft(ref.filters[held], nfft, axis=-1))[..., band]
    for method in ("nearest", "barycentric"):
        for taps in ((64, 192) if quick else (32, 64, 128, 192, 256)):
            h = HrtfInterpolator(sub, sr, taps=taps)
            h.lookup_spectra(dirs, nfft, method)  # warm-up: grid table and spectra are built once
            (spec, _), t = _timed(lambda: h.lookup_spectra(np.tile(dirs, (2, 1))[:64], nfft, method), reps=50)
            mag = np.abs(spec[: len(dirs)])[..., band]
            lsd = np.sqrt(np.mean((20 * np.log10((mag + 1e-9) / (truth + 1e-9))) ** 2, axis=-1))
            rows.append({"setting": f"{method}/{taps}", "error": float(np.mean(lsd)), "time_s": t})
    return {"knob": "hrtf_interpolation/taps", "error_metric": "log-spectral distance (dB, 200 Hz-16 kHz) of a "
            "held-out measured KEMAR direction interpolated from the others; time: 64 lookups", "rows": rows}


def _render_ir(cfg, probes, src, lis, seconds):
    from sonicverse_core.acoustics.renderer import AcousticRenderer

    r = AcousticRenderer(None, cfg, probes=probes)
    imp = np.zeros(int(seconds * cfg.sample_rate), np.float32)
    imp[0] = 1.0
    r.add_source(imp, src, loop=False)
    r.add_listener(lis)
    t0 = time.perf_counter()
    y = r.render(seconds)[0]
    return y, (time.perf_counter() - t0) / int(np.ceil(seconds * cfg.sample_rate / cfg.block))


def _shoebox_probe(dims, material):
    from sonicverse_core.acoustics.probes import Probe, eyring_rt60
    from sonicverse_core.scene.spec import load_scene

    s = load_scene(f"shoebox:{dims[0]}x{dims[1]}x{dims[2]}?material={material}")
    ey = eyring_rt60(dims, s.metadata["surface_materials"])
    return Probe(np.array(dims) / 2, ey, ey, np.zeros(3), np.array(dims, float), (material,) * 6, 1.0)


@contextlib.contextmanager
def _raw_images(pra):
    """pyroomacoustics' impulse responses without its DC-removing high-pass (a 10 Hz zero-phase filter applied to
    every response by default): on a response of many positive image pulses it leaves a pedestal that takes 5-10% off
    each pulse's energy once both are low-passed, which an echogram comparison counts as error (order 2 in a shoebox:
    12.7% with it, 1.5% without). Ours has no such filter. Restores the setting afterwards."""
    was = pra.constants.get("rir_hpf_enable")
    pra.constants.set("rir_hpf_enable", False)
    try:
        yield
    finally:
        pra.constants.set("rir_hpf_enable", was)


def _early(quick: bool):
    import pyroomacoustics as pra

    from sonicverse_core.acoustics.early import wall_reflectance
    from sonicverse_core.acoustics.renderer import RenderConfig

    dims, mat = (6.0, 4.0, 3.0), "PlasterRough"
    probe = _shoebox_probe(dims, mat)
    src, lis = np.array([1.7, 1.3, 1.2]), np.array([4.1, 2.6, 1.6])
    fs = 48000
    refl = wall_reflectance(probe.box_materials)[0]
    rows = []
    for order in (1, 2):
        room = pra.ShoeBox(list(dims), fs=fs, materials=pra.Material(float(1 - refl ** 2)), max_order=order,
                           air_absorption=False)
        room.add_source(src.tolist())
        room.add_microphone(lis.tolist())
        with _raw_images(pra):
            room.compute_rir()
        h_ref = np.asarray(room.rir[0][0])  # pyroomacoustics scales image amplitudes as 1 / r, as we do
        delay = pra.constants.get("frac_delay_length") // 2  # its fractional-delay filters' latency
        h_ref = h_ref[delay:]
        cfg = RenderConfig(output="mono", occlusion=False, late_reverb=False, er_order=order, near_field_gain=0,
                           max_distance=5000)
        _render_ir(cfg, [probe], src, lis, 0.02)  # warm-up (compiled kernels)
        y, t = _render_ir(cfg, [probe], src, lis, 0.1)
        h = y[0].astype(float) * np.sqrt(2)  # the mono output's 1/sqrt(2) per ear
        n = int(0.06 * fs)
        bins = 48
        # compared below 4 kHz: both use interpolating fractional delays that differ near Nyquist
        from scipy.signal import butter, sosfiltfilt

        sos = butter(6, 4000, fs=fs, output="sos")
        h = sosfiltfilt(sos, np.r_[h, np.zeros(n)][: 2 * n])
        h_ref = sosfiltfilt(sos, np.r_[h_ref, np.zeros(2 * n)][: 2 * n])
        e1 = np.add.reduceat(h[:n] ** 2, np.arange(0, n, bins))
        e0 = np.add.reduceat(h_ref[:n] ** 2, np.arange(0, n, bins))
        rows.append({"setting": f"order {order}", "error": float(np.sum(np.abs(e1 - e0)) / np.sum(e0)),
                     "time_s": t})
    return {"knob": "early_reflection_order", "error_metric": "echogram error sum|E - E_ref| / sum E_ref (1 ms "
            "bins, 0-60 ms, both low-passed at 4 kHz) vs pyroomacoustics ShoeBox image sources of the same order and wall reflection; "
            "time: per 256-frame block", "rows": rows}


def _early_geometry(quick: bool):
    """Early reflections in the L-shaped room (one plaster-like reflection factor on every surface): images of the
    listener's room's own walls vs of the probe's proxy box, against pyroomacoustics' image sources of the room's
    polygon of the same order, with the source in view and round the corner."""
    import pyroomacoustics as pra
    from scipy.signal import butter, sosfiltfilt

    from sonicverse_core.acoustics.early import wall_reflectance
    from sonicverse_core.acoustics.probes import scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
    from sonicverse_core.scene import reference as ref
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("builtin:l-room")
    probes = scene_probes(scene)
    fs = 48000
    corners = np.array([(0, 0), (6, 0), (6, 3), (3, 3), (3, 6), (0, 6)], float).T
    sos = butter(6, 4000, fs=fs, output="sos")
    pairs = [((5.0, 1.5, 1.5), (1.5, 1.5, 1.5)), ((5.0, 1.5, 1.5), (1.5, 5.0, 1.5))]  # in view, round the corner
    mats = {name: pra.Material(float(1 - wall_reflectance([m])[0] ** 2))
            for name, m in (("walls", ref.WALLS), ("floor", ref.FLOOR), ("ceiling", ref.CEILING))}
    rows = []
    for order in ((1,) if quick else (1, 2)):
        refs = []
        for src, lis in pairs:
            hs = []
            for o in (order, 0):  # the reflections only: its images of this order less the direct sound
                room = pra.Room.from_corners(corners, fs=fs, max_order=o, materials=mats["walls"],
                                             air_absorption=False)
                room.extrude(3.0, materials={"floor": mats["floor"], "ceiling": mats["ceiling"]})
                room.add_source(list(src))
                room.add_microphone(np.array(lis, float)[:, None])
                with _raw_images(pra):
                    room.compute_rir()
                hs.append(np.asarray(room.rir[0][0])[pra.constants.get("frac_delay_length") // 2:])
            h = np.zeros(int(0.2 * fs))
            h[:min(len(hs[0]), len(h))] += hs[0][:len(h)]
            h[:min(len(hs[1]), len(h))] -= hs[1][:len(h)]
            refs.append(h)
        for mode in ("box", "room"):
            cfg = RenderConfig(output="mono", late_reverb=False, er_order=order, er_images=mode, near_field_gain=0,
                               max_distance=5000)
            err, tt = [], []
            for (src, lis), h_ref in zip(pairs, refs):
                imp = np.zeros(int(0.1 * fs), np.float32)
                imp[0] = 1.0
                ys = []
                for c in (cfg, RenderConfig(**{**cfg.__dict__, "early_reflections": False})):
                    r = AcousticRenderer(scene, c, probes=probes)
                    r.add_source(imp, src, loop=False)
                    r.add_listener(lis)
                    ys.append(r.render(0.1)[0][0].astype(float) * np.sqrt(2))  # mono: 1/sqrt(2) per ear
                r = AcousticRenderer(scene, cfg, probes=probes)  # the time: a steady source, kernels warm
                r.add_source(np.random.default_rng(0).normal(0, 0.1, fs).astype(np.float32), src, loop=True)
                r.add_listener(lis)
                r.render(0.05)
                t0 = time.perf_counter()
                r.render(0.5)
                tt.append((time.perf_counter() - t0) / int(np.ceil(0.5 * fs / cfg.block)))
                h = ys[0] - ys[1]  # the reflections only (the renderer is deterministic)
                n, bins = int(0.06 * fs), 48
                h = sosfiltfilt(sos, np.r_[h, np.zeros(2 * n)][: 2 * n])
                h_ref = sosfiltfilt(sos, np.r_[h_ref, np.zeros(2 * n)][: 2 * n])
                e1 = np.add.reduceat(h[:n] ** 2, np.arange(0, n, bins))
                e0 = np.add.reduceat(h_ref[:n] ** 2, np.arange(0, n, bins))
                err.append(float(np.sum(np.abs(e1 - e0)) / np.sum(e0)))
            rows.append({"setting": f"{mode}, order {order}", "error": float(np.mean(err)),
                         "error_per_case": {"in view": err[0], "round the corner": err[1]},
                         "time_s": float(np.mean(tt))})
    return {"knob": "early_reflection_geometry", "error_metric": "echogram error sum|E - E_ref| / sum E_ref (1 ms "
            "bins, 0-60 ms, low-passed at 4 kHz; mean of a source in view and one round the corner of the L-shaped "
            "room) of the reflections alone (each simulator's response less its direct sound) vs pyroomacoustics' image "
            "sources of the room's polygon, same order and reflection factors; time: per 256-frame block",
            "rows": rows}


def _band_rt60(y, fs):
    """RT60 (s) per octave band 250 Hz-4 kHz of an impulse response by Schroeder integration (T20)."""
    from scipy.signal import butter, sosfiltfilt

    out = []
    for fc in (250, 500, 1000, 2000, 4000):
        sos = butter(3, [fc / np.sqrt(2), fc * np.sqrt(2)], "bandpass", fs=fs, output="sos")
        e = sosfiltfilt(sos, y) ** 2
        sch = np.cumsum(e[::-1])[::-1]
        db = 10 * np.log10(np.maximum(sch / sch[0], 1e-30))
        t = np.arange(len(y)) / fs
        m = (db <= -5) & (db >= -25)
        out.append(-60 / np.polyfit(t[m], db[m], 1)[0])
    return np.array(out)


def _reverb(quick: bool):
    from sonicverse_core.acoustics.renderer import RenderConfig

    probe = _shoebox_probe((8.0, 6.0, 3.0), "PlasterRough")
    target = probe.rt60[3:8]
    rows = []
    # the convolution's tails in long partitions after their first few (the default) or all in one-block ones:
    # the same convolution, the one cheaper
    for setting, method, parts in (("fdn", "fdn", "auto"), ("convolution", "convolution", "auto"),
                                   ("convolution uniform", "convolution", "uniform")):
        cfg = RenderConfig(output="stereo", occlusion=False, early_reflections=False, reverb=method,
                           tail_partitions=parts)
        y, t = _render_ir(cfg, [probe], [2.0, 2.0, 1.5], [5.0, 3.5, 1.5], 2.5)
        rt = _band_rt60(y[0].astype(float)[int(0.03 * 48000):], 48000)
        rows.append({"setting": setting, "error": float(np.mean(np.abs(rt / target - 1))), "time_s": t,
                     "rt60_measured": np.round(rt, 3).tolist(), "rt60_target": np.round(target, 3).tolist()})
    return {"knob": "reverb_method", "error_metric": "mean |RT60_rendered / RT60_probe - 1| over 250 Hz-4 kHz "
            "octaves (Schroeder T20 of the rendered impulse response); time: per 256-frame block", "rows": rows}


def _blocks(quick: bool):
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    fs, seconds = 48000, 1.0
    x = np.random.default_rng(0).normal(size=int(fs * 1.5)).astype(np.float32) * 0.1

    def run(block):
        r = AcousticRenderer(None, RenderConfig(block=block, occlusion=False, late_reverb=False))
        s = r.add_source(x, (2.0, -3.0, 0.0), loop=False)
        r.add_listener((0, 0, 0))
        out, n = [], int(np.ceil(seconds * fs / block))
        t0 = time.perf_counter()
        for i in range(n):
            s.position = (2.0, -3.0 + 2.0 * (i + 1) * block / fs, 0.0)  # 2 m/s past the listener
            out.append(r.render_block()[0])
        return np.concatenate(out, 1)[:, : int(seconds * fs)], (time.perf_counter() - t0) / seconds

    ref, _ = run(16)
    rows = []
    for b in ((64, 256, 1024) if quick else (32, 64, 128, 256, 512, 1024, 2048)):
        y, t = run(b)
        rows.append({"setting": b, "error": float(np.sqrt(np.mean((y - ref) ** 2) / np.mean(ref ** 2))),
                     "time_s": t})
    return {"knob": "block_size", "error_metric": "relative RMS difference to block 16 of a source passing at "
            "2 m/s (pose updated once per block); time: per second of audio", "rows": rows}


def _path_cell(quick: bool):
    """Propagation paths' grid: path length and arrival direction round the L-room's corner vs the exact geometry."""
    from sonicverse_core.acoustics.paths import PathGraph
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("builtin:l-room")
    rng = np.random.default_rng(0)
    corner = np.array([3.0, 3.0])
    # sources in the east arm, listeners in the north arm, out of each other's sight
    src = np.c_[rng.uniform(4.0, 5.7, 40), rng.uniform(0.4, 2.6, 40)]
    lis = np.c_[rng.uniform(0.4, 2.6, 40), rng.uniform(4.0, 5.7, 40)]
    exact = np.linalg.norm(src - corner, axis=1) + np.linalg.norm(lis - corner, axis=1)
    PathGraph(scene, 0.3).path(src[0], lis[0])  # compiles the kernels (once per machine: cached on disk)
    rows = []
    for cell in ((0.1, 0.2) if quick else (0.05, 0.1, 0.2, 0.3)):
        g, t_bake = _timed(lambda: PathGraph(scene, cell))
        t0 = time.perf_counter()
        res = [g.path(s, li) for s, li in zip(src, lis)]
        t_query = (time.perf_counter() - t0) / len(src)
        ok = [r is not None for r in res]
        length = np.array([r.length if r is not None else np.nan for r in res])
        last = np.array([r.last if r is not None else (np.nan, np.nan) for r in res])
        d_exact = np.degrees(np.arctan2(*(corner - lis).T[::-1]))
        d_ours = np.degrees(np.arctan2(*(last - lis).T[::-1]))
        rows.append({"setting": cell, "error": float(np.nanmean(np.abs(length / exact - 1))), "time_s": t_bake,
                     "query_s": t_query, "found": float(np.mean(ok)),
                     "direction_error_deg": float(np.nanmean(np.abs((d_ours - d_exact + 180) % 360 - 180)))})
    return {"knob": "path_cell", "error_metric": "mean |path length / exact - 1| round the L-room's corner (40 "
            "source-listener pairs; those the grid lets see each other past the corner take the straight line and "
            "are not counted: 'found'; direction error of the last bend in the row); "
            "time: the scene's path graph bake", "rows": rows}


def utd_transition(X):
    """The uniform theory of diffraction's transition function (Kouyoumjian & Pathak 1974):
    F(X) = 2 j sqrt(X) e^(jX) int_sqrt(X)^inf e^(-j tau^2) d tau, from the Fresnel integrals; F -> 1 for large X."""
    from scipy.special import fresnel

    X = np.asarray(X, float)
    S, C = fresnel(np.sqrt(2.0 * X / np.pi))
    return 2j * np.sqrt(X) * np.exp(1j * X) * np.sqrt(np.pi / 2) * ((0.5 - C) - 1j * (0.5 - S))


def utd_wedge_loss_db(rho, r, phi_s, phi_l, f, n: float, c: float = 343.0):
    """dB below the free field at distance rho + r of the field a rigid wedge of exterior angle n pi diffracts from
    a point source at distance rho from its edge to a listener at r, both in the plane normal to the edge, at angles
    phi_s and phi_l (radians) from the wedge's first face through the free space (UTD, Kouyoumjian & Pathak 1974,
    hard faces: the four terms added; spherical spreading L = rho r / (rho + r)). ``f`` scalar or array (Hz)."""
    k = 2 * np.pi * np.asarray(f, float) / c
    L = rho * r / (rho + r)
    tot = 0.0
    for beta in (phi_l - phi_s, phi_l + phi_s):
        for sgn in (1.0, -1.0):
            N = np.round((beta + sgn * np.pi) / (2 * np.pi * n))
            a = 2 * np.cos((2 * n * np.pi * N - beta) / 2) ** 2
            tot = tot + utd_transition(k * L * a) / np.tan((np.pi + sgn * beta) / (2 * n))
    D = np.abs(tot) / (2 * n * np.sqrt(2 * np.pi * k))
    return -20 * np.log10(D / np.sqrt(L))


def _diffraction(quick: bool):
    """The paths' bend loss round the L-room's corner (40 source-listener pairs out of each other's sight) against
    the uniform theory of diffraction for that corner: a rigid 90-degree wedge (exterior angle 270 degrees), per
    octave band 250 Hz-4 kHz, the energy over each band (17 frequencies)."""
    from sonicverse_core.acoustics.paths import DIFFRACTION_MODELS, PathGraph
    from sonicverse_core.scene.materials import BANDS
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("builtin:l-room")
    rng = np.random.default_rng(0)
    corner = np.array([3.0, 3.0])  # the wedge's edge; its faces run east (y = 3) and north (x = 3) of it
    src = np.c_[rng.uniform(4.0, 5.7, 40), rng.uniform(0.4, 2.6, 40)]
    lis = np.c_[rng.uniform(0.4, 2.6, 40), rng.uniform(4.0, 5.7, 40)]
    g = PathGraph(scene, 0.1)
    g.path(src[0], lis[0])  # compiles the kernels (once per machine: cached on disk)

    def phi(p):  # from the east face, clockwise through the free space (0 .. 3 pi / 2)
        return (-np.arctan2(p[1] - corner[1], p[0] - corner[0])) % (2 * np.pi)

    bands = BANDS[3:8]
    ref = {}
    for i, (s, li) in enumerate(zip(src, lis)):
        rho, r = np.linalg.norm(s - corner), np.linalg.norm(li - corner)
        e = [np.mean(10 ** (-utd_wedge_loss_db(rho, r, phi(s), phi(li), fc * 2 ** np.linspace(-0.5, 0.5, 17), 1.5)
                            / 10)) for fc in bands]
        ref[i] = -10 * np.log10(e)
    rows = []
    for model in DIFFRACTION_MODELS:
        t0 = time.perf_counter()
        res = [g.path(s, li, model) for s, li in zip(src, lis)]
        t = (time.perf_counter() - t0) / len(src)
        err = [np.abs(-20 * np.log10(p.amplitude[3:8]) - ref[i]) for i, p in enumerate(res) if p is not None]
        rows.append({"setting": model, "error": float(np.mean(err)), "time_s": t,
                     "error_per_band_db": np.round(np.mean(err, axis=0), 2).tolist(),
                     "utd_loss_per_band_db": np.round(np.mean([ref[i] for i, p in enumerate(res) if p is not None],
                                                              axis=0), 2).tolist(),
                     "pairs": len(err)})
    return {"knob": "diffraction_model", "error_metric": "mean |bend loss - UTD's| (dB) per octave band 250 Hz-4 kHz "
            "round the L-room's corner (a rigid 90-degree wedge; the pairs the grid finds a path for); time: a "
            "path query", "rows": rows}


def _door_mix(quick: bool):
    """When a door's move reaches the late reverb's mix (``LateReverb.door_delay``, default ``late.DOOR_MIX_DELAY``
    blocks after the block that casts its occlusion and paths): the binaural output after each move against the
    re-mix made at once (0), and what the costliest of the three blocks after a move takes."""
    from app.bench.engine import _audio_scene
    from sonicverse_core.acoustics.late import DOOR_MIX_DELAY
    from sonicverse_core.acoustics.renderer import RenderConfig

    moves, gap = (6, 40) if quick else (18, 40)  # 40 blocks of 256 frames between moves: 0.21 s
    rows, ref = [], None
    for delay in sorted({0, 1, DOOR_MIX_DELAY}):
        r = _audio_scene("builtin:apartment", 16, 0, RenderConfig(sample_rate=48000, block=256))
        r.late.door_delay = delay
        r.warm_kernels()
        doors = r.scene.doors
        for _ in range(20):
            r.render_block()
        energy, cost = np.zeros((moves, gap)), np.zeros((moves, 3))
        for m in range(moves):
            d = doors[m % len(doors)]
            r.set_doors({d.name: 0.0 if d.open_fraction > 0.5 else 1.0})
            for b in range(gap):
                t0 = time.perf_counter()
                out = r.render_block()[0]
                if b < 3:
                    cost[m, b] = time.perf_counter() - t0
                energy[m, b] = float(np.mean(np.square(out, dtype=np.float64)))
        db = 10 * np.log10(energy + 1e-30)
        if ref is None:
            ref = db
        err = np.abs(db - ref).max(axis=1)  # per move, the block furthest from the re-mix made at once
        rows.append({"setting": delay, "error": float(np.mean(err)), "time_s": float(np.median(cost.max(axis=1))),
                     "max_error_db": round(float(err.max()), 3),
                     "median_block_s_after_a_move": np.round(np.median(cost, axis=0), 6).tolist()})
    return {"knob": "door_mix_delay", "error_metric": "mean over door moves of the largest |dB| difference of a "
            "256-frame block's binaural energy in the 0.21 s after the move from the late re-mix made at once (16 "
            "sources in the apartment, the listener still); time: the costliest of the three blocks after a move "
            "(median over the moves)", "rows": rows}


def bench_accuracy(reference_rays: int = 1_000_000, quick: bool = False, plot: str | None = None) -> dict:
    from sonicverse_core.progress import progress

    steps = [lambda: _rays_and_bounces(reference_rays, quick), lambda: [_scattering(quick)],
             lambda: [_late_model(quick)], lambda: [_neighbour_tails(quick)],
             lambda: [_probes(quick)], lambda: [_hrtf(quick)],
             lambda: [_early(quick)], lambda: [_early_geometry(quick)], lambda: [_reverb(quick)], lambda: [_blocks(quick)], lambda: [_path_cell(quick)],
             lambda: [_diffraction(quick)], lambda: [_door_mix(quick)]]
    knobs = [k for step in progress(steps, desc="accuracy knobs") for k in step()]
    for k in knobs:
        front = _pareto([(r["error"], r["time_s"]) for r in k["rows"]])
        for i, r in enumerate(k["rows"]):
            r["pareto"] = i in front
            r["error"] = round(r["error"], 5)
            r["time_s"] = round(r["time_s"], 6)
    if plot:
        _plot(knobs, plot)
    return {"bench": "accuracy", "knobs": knobs, "plot": plot}


def _plot(knobs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 4
    rows = int(np.ceil(len(knobs) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows))
    for ax, k in zip(axes.ravel(), knobs):
        e = np.array([r["error"] for r in k["rows"]])
        t = np.array([r["time_s"] for r in k["rows"]])
        p = np.array([r["pareto"] for r in k["rows"]])
        ax.scatter(t, e, c=np.where(p, "C3", "C0"), zorder=3)
        order = np.argsort(t[p])
        ax.plot(t[p][order], e[p][order], "C3--", lw=1, label="Pareto front")
        for r, ti, ei in zip(k["rows"], t, e):
            ax.annotate(str(r["setting"]), (ti, ei), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_title(k["knob"], fontsize=9)
        ax.set_xlabel("time (s)", fontsize=8)
        ax.set_ylabel("error", fontsize=8)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(knobs):]:
        ax.axis("off")
    fig.tight_layout()
    from pathlib import Path

    Path(path).parent.mkdir(parents=True, exist_ok=True)  # the argument's promise: created when writing
    fig.savefig(path, dpi=110)
    plt.close(fig)
