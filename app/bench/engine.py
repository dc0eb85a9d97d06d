"""Benchmarks: each measures against a reference in the same run and returns a JSON-able dict."""
from __future__ import annotations

import time

import numpy as np


def _rate(fn, n_items: int, min_time: float = 0.5, max_reps: int = 50) -> float:
    fn()  # warm-up
    reps, t0 = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        dt = time.perf_counter() - t0
        if dt >= min_time or reps >= max_reps:
            return n_items * reps / dt


def bench_rays(spec: str = "builtin:apartment", n_rays: int = 200_000, n_reference: int = 2_000,
               seed: int = 0) -> dict:
    """Rays per second through the Embree caster vs trimesh's pure-numpy caster, same scene, same kind of rays."""
    from sonicverse_core.geometry.raycast import RayCaster
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(spec)
    mesh = scene.static_mesh()
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds
    o = rng.uniform(lo + 0.2, hi - 0.2, (n_rays, 3))
    d = rng.normal(size=(n_rays, 3))
    embree = RayCaster(mesh, "embree")
    numpy_ = RayCaster(mesh, "numpy")
    r_embree = _rate(lambda: embree.first_hit(o, d), n_rays)
    r_numpy = _rate(lambda: numpy_.first_hit(o[:n_reference], d[:n_reference]), n_reference, max_reps=3)
    h1 = embree.first_hit(o[:n_reference], d[:n_reference])
    h2 = numpy_.first_hit(o[:n_reference], d[:n_reference])
    both = h1.hit & h2.hit
    return {
        "bench": "rays", "scene": spec, "triangles": len(mesh),
        "embree_rays_per_s": round(r_embree), "numpy_rays_per_s": round(r_numpy),
        "speedup": round(r_embree / r_numpy, 1),
        "agreement": {"same_hit_fraction": float(np.mean(h1.hit == h2.hit)),
                      "max_distance_error_m": float(np.max(np.abs(h1.distance[both] - h2.distance[both])))
                      if np.any(both) else 0.0},
    }


def _audio_scene(spec: str, n_sources: int, seed: int, cfg, per_room: bool = True, listener_room: str | None = None):
    """A renderer over ``spec`` with n sound-bank sources on random navigable points and one listener (in room
    ``listener_room`` when given: the first navigable point drawn there)."""
    from assets_manifest import soundbank
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(spec)
    if listener_room is not None and all(r.name != listener_room for r in scene.rooms):
        from sonicverse_core.errors import ConfigError

        raise ConfigError(f"no room '{listener_room}' in {spec}; its rooms: "
                          f"{', '.join(r.name for r in scene.rooms) or 'none'}")
    probes = scene_probes(scene, BakeConfig(per_room=per_room)) if cfg.late_reverb or cfg.early_reflections else None
    r = AcousticRenderer(scene, cfg, probes=probes)
    rng = np.random.default_rng(seed)
    grid = NavGrid(scene)
    pts = grid.sample(rng, n_sources + 1)
    for i in range(n_sources):
        cat = soundbank.CATEGORIES[i % len(soundbank.CATEGORIES)]
        r.add_source(soundbank.sound(cat, i % 3), np.r_[pts[i, :2], 1.0], sample_rate=soundbank.SAMPLE_RATE,
                     gain=0.1)
    # the listener: the last point drawn, or a point drawn after the sources' in its room (same sources either way)
    at = pts[-1, :2] if listener_room is None else grid.sample(rng, 1, room=listener_room)[0, :2]
    r.add_listener(np.r_[at, 1.5], 0.0)
    return r


def bench_audio(n_sources: int = 64, seconds: float = 8.0, spec: str = "builtin:apartment", seed: int = 0,
                sample_rate: int = 48000, block: int = 256, reference_blocks: int = 20, per_room: bool = True,
                reverb: str = "convolution", er_images: str = "room", er_order: int = 1,
                neighbour_tails: int | None = None, listener_room: str | None = None, walk: float = 0.15,
                tail_partitions: str = "auto", breakdown: bool = False, door_every: float | None = None) -> dict:
    """Per-block cost of the full pipeline (HRTF, occlusion, propagation paths, early reflections, coupled late
    reverb) as a fraction of the block's duration (and, per listener, how many sources it hears along paths, how
    many room tails it convolves and from how many rooms sources send to it), with the listener walking and turning every block (so every source's direction, delay and
    occlusion changes), against a naive reference in the same run: per source and ear, a full scipy convolution of
    the block with a 0.5 s binaural room impulse response (overlap-add). ``per_room``: probes baked per room and
    the rooms' decays coupled (``BakeConfig.per_room``); ``reverb``: "convolution" or "fdn"; ``er_images``,
    ``er_order``: the early reflections' geometry and order, ``neighbour_tails``: coupled rooms heard apart besides
    the slowest mode's (``RenderConfig``); ``listener_room``: the room the listener starts in (default: anywhere);
    ``walk``: the listener's speed (m/s) round a 0.3 m circle (a person walking in VR: about 1-1.4 m/s; the
    occlusion recast and the late re-mix follow the listener's steps, so they run more often the faster it walks);
    ``tail_partitions``: the convolution tails' partitions (``RenderConfig.tail_partitions``); ``breakdown``: also
    time each subsystem's share of the timed blocks (``per_subsystem``: mean fraction of the block per subsystem,
    "other" the sources' reads, the smoothing, the limiter; one clock read either side of each subsystem's render,
    so the blocks' own figures include that little more; ``late_remix``: how often the coupled rooms' late reverb
    mixed its tails again as the listener moved, its mean cost and its share of the block, inside the late
    reverb's). ``blocks_over_real_time``: how many timed blocks took longer than their duration (a dropout in a live
    stream); of them, how many had their thread on the CPU for under half the block's wall time (held off it:
    preempted, or waiting in the kernel); and the first 20 blocks' indices.
    The walk is the same in every run, so a block that is late because of the renderer is late again at the same
    index in a re-run, and a stall of the machine is not (a virtual CPU that its host stops may still count as the
    thread's CPU time).
    ``door_every``: every that many seconds of audio one of the scene's doors (in turn) opens if shut or shuts if
    open, as the live audio core applies it (:meth:`app.audio_rt.core.RenderCore._apply_doors`): after a block,
    the door moved and the occlusion's geometry prepared (``doors.apply``, a fraction of the block's duration),
    then the next block renders the change (``doors.block``: the occlusion and paths; the early reflections'
    walls are cast again in the block after it, ``doors.next_block``, and the late reverb takes the rooms' new
    balance in the one after that, ``doors.third_block``). A live stream must fit each in a block (the live core
    spends the first after writing a block's output, in the same callback); ``over_real_time`` counts those that
    did not."""
    from scipy.signal import oaconvolve

    from sonicverse_core.acoustics.renderer import RenderConfig

    if neighbour_tails is None:  # the renderer's default
        neighbour_tails = RenderConfig.neighbour_tails
    cfg = RenderConfig(sample_rate=sample_rate, block=block, reverb=reverb, er_images=er_images, er_order=er_order,
                       neighbour_tails=neighbour_tails, tail_partitions=tail_partitions)
    r = _audio_scene(spec, n_sources, seed, cfg, per_room, listener_room)
    spent: dict[str, float] = {}
    if breakdown:  # each subsystem's render timed where the renderer calls it (an instance attribute, this run only)
        for part in r.parts:
            def timed(st, ls, lis_, out, _render=part.render, _name=part.name):
                t0 = time.perf_counter()
                _render(st, ls, lis_, out)
                spent[_name] = spent.get(_name, 0.0) + time.perf_counter() - t0
            part.render = timed
            if hasattr(part, "_modal_mix"):  # the late reverb's re-mix (coupled rooms), timed per call inside it
                def remix(*a, _mix=part._modal_mix):
                    t0 = time.perf_counter()
                    res = _mix(*a)
                    spent["late re-mix"] = spent.get("late re-mix", 0.0) + time.perf_counter() - t0
                    spent["late re-mixes"] = spent.get("late re-mixes", 0) + 1
                    return res
                part._modal_mix = remix
    lis = r.listeners[0]
    start = lis.position.copy()
    block_s = block / sample_rate
    n_blocks = int(seconds / block_s)
    omega = walk / 0.3  # rad/s round the circle (0.5 at the default 0.15 m/s)
    times, cpu = np.empty(n_blocks), np.empty(n_blocks)  # each block's wall time and its thread's CPU time
    paths, reverbs, sending = (np.zeros(n_blocks, int) for _ in range(3))
    doors = r.scene.doors if door_every else []
    if door_every and not doors:
        from sonicverse_core.errors import ConfigError

        raise ConfigError(f"--door-every: {spec} has no doors")
    every = max(1, int(round(door_every / block_s))) if doors else 0
    applied, door_blocks, next_blocks, third_blocks, door_at = [], [], [], [], set()
    from sonicverse_core.progress import progress

    import gc

    # as the live audio workers render (app.audio_rt.worker): the collector frozen and off, so that its pauses,
    # which a live callback never sees, do not land in the timed blocks
    collecting, frozen = gc.isenabled(), gc.get_freeze_count()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        # as the live audio workers do before their stream opens: every kernel a block can reach compiled (or
        # loaded) now, not on its first use in a timed block (one took up to 128 times a block's duration there)
        r.warm_kernels()
        for i in progress(range(-50, n_blocks), desc="audio blocks"):  # 50 warm-up blocks (timed per block, below)
            t = (i + 50) * block_s
            pos = start + np.array([0.3 * np.sin(omega * t), 0.3 * np.cos(omega * t), 0.0])  # a walk (slow by
            r.set_listener(lis, pos, 40.0 * t % 360.0)  # default) and a head turning at 40 deg/s
            if i == 0:
                spent.clear()  # the warm-up blocks are not counted
            c0 = time.thread_time()
            t0 = time.perf_counter()
            r.render_block()
            if i >= 0 and i in door_at:
                door_blocks.append((time.perf_counter() - t0) / block_s)
            if i >= 0 and i - 1 in door_at:
                next_blocks.append((time.perf_counter() - t0) / block_s)
            if i >= 0 and i - 2 in door_at:
                third_blocks.append((time.perf_counter() - t0) / block_s)
            if every and i >= 0 and (i + 1) % every == 0 and i + 1 < n_blocks:  # after this block: a door moves
                d = doors[len(applied) % len(doors)]
                a0 = time.perf_counter()
                r.set_doors({d.name: 0.0 if d.open_fraction > 0.5 else 1.0})
                applied.append((time.perf_counter() - a0) / block_s)
                door_at.add(i + 1)
            if i >= 0:
                times[i] = time.perf_counter() - t0
                cpu[i] = time.thread_time() - c0
                paths[i], reverbs[i], sending[i] = (r.stats[k] for k in ("paths", "room_reverbs", "rooms_sending"))
    finally:
        if not frozen:  # a caller's own frozen objects stay frozen
            gc.unfreeze()
        if collecting:
            gc.enable()
    frac = times / block_s
    # naive reference: direct convolution of every source's block with a 0.5 s BRIR per ear
    brir = np.random.default_rng(seed).normal(size=(2, int(0.5 * sample_rate))).astype(np.float32)
    x = np.random.default_rng(seed + 1).normal(size=(n_sources, block)).astype(np.float32)
    ref = []
    for _ in range(reference_blocks):
        t0 = time.perf_counter()
        acc = np.zeros((2, block + brir.shape[1] - 1), np.float32)
        for k in range(n_sources):
            for e in range(2):
                acc[e] += oaconvolve(x[k], brir[e])
        ref.append(time.perf_counter() - t0)
    ref_frac = np.array(ref) / block_s
    res = {
        "bench": "audio", "scene": spec, "sources": n_sources, "sample_rate": sample_rate, "block": block,
        "per_room": per_room, "reverb": reverb, "er_images": er_images, "er_order": er_order,
        "neighbour_tails": neighbour_tails, "listener_room": listener_room, "walk_m_per_s": walk,
        "tail_partitions": tail_partitions,
        "garbage_collector": "frozen and off while blocks are timed, as in the live audio workers",
        "kernels": "warmed before the first block (AcousticRenderer.warm_kernels), as in the live audio workers",
        "blocks": n_blocks, "subsystems": r.subsystems,
        "realtime_fraction": {"median": round(float(np.median(frac)), 4), "p99": round(float(np.percentile(frac, 99)), 4),
                              "max": round(float(frac.max()), 4)},
        "reference": {"method": "per-source scipy.signal.oaconvolve with a 0.5 s BRIR per ear",
                      "realtime_fraction": {"median": round(float(np.median(ref_frac)), 4),
                                            "p99": round(float(np.percentile(ref_frac, 99)), 4)}},
        "speedup_vs_reference": round(float(np.median(ref_frac) / np.median(frac)), 1),
        # a block over its duration is a dropout in a live stream: the renderer's cost, or the machine's stall?
        "blocks_over_real_time": {"count": int((frac > 1).sum()),
                                  "thread_off_the_cpu": int(((frac > 1) & (cpu < 0.5 * times)).sum()),
                                  "at": np.flatnonzero(frac > 1)[:20].tolist()},
        "occlusion": {k: r.stats[k] for k in ("occlusion_rays", "occlusion_skipped")},
        "per_listener": {"sources_heard_along_paths": {"mean": round(float(paths.mean()), 2), "max": int(paths.max())},
                         "room_reverbs_convolved": {"mean": round(float(reverbs.mean()), 2),
                                                    "max": int(reverbs.max())},
                         "rooms_sending_to_the_reverb": {"mean": round(float(sending.mean()), 2),
                                                         "max": int(sending.max())}},
    }
    if every:
        ab, db, nb, tb = (np.array(v) for v in (applied, door_blocks, next_blocks, third_blocks))
        res["doors"] = {"every_s": door_every, "moves": len(ab),
                        **{k: {"median": round(float(np.median(v)), 4), "max": round(float(v.max()), 4)}
                           for k, v in (("apply", ab), ("block", db), ("next_block", nb), ("third_block", tb))
                           if len(v)},
                        "over_real_time": int(sum((v > 1).sum() for v in (ab, db, nb, tb)))}
    if breakdown:
        mixes, mix_s = spent.pop("late re-mixes", 0), spent.pop("late re-mix", 0.0)  # inside the late share
        shares = {k: v / n_blocks / block_s for k, v in spent.items()}
        res["per_subsystem"] = {**{k: round(v, 4) for k, v in sorted(shares.items(), key=lambda kv: -kv[1])},
                                "other": round(float(frac.mean()) - sum(shares.values()), 4),
                                "mean_block": round(float(frac.mean()), 4)}
        res["late_remix"] = {"count": int(mixes), "us_each": round(1e6 * mix_s / mixes, 1) if mixes else None,
                             "share": round(mix_s / n_blocks / block_s, 4)}
    return res
