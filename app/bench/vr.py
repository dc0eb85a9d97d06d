"""`sonicverse bench vr`: stereo frames per second of the headless loop, with references measured in the same run.

Per eye size: the loop as shipped (the home's look: textures, light baked per vertex, FLAT shader, single-sampled,
no depth read-back), the flat look (one colour per face; what the textures and the baked light cost), the same with 4x MSAA (the error of leaving it out: mean absolute pixel difference, 0-255 levels), and
stock pyrender (lit PBR shader, 4x MSAA, colour + depth read-back) as the reference the speed-up is measured
against. Then the audio-only loop (tracking + binaural audio rendered by the frame clock); room culling against the
whole scene (:func:`room_culling`, also on the home subdivided to scanned-house triangle counts); and the live audio
pipeline (app/audio_rt on a private JACK dummy server) while the loop renders 512x512 stereo flat out: xruns and
callback timing.
"""
from __future__ import annotations

import os
import time

import numpy as np


def _session(scene: str, size, views=True, audio="none", msaa=False, device=None, task=None, realtime=False):
    from app.vr.headless import HeadlessBackend
    from app.vr.session import SessionConfig, VRSession

    robots = 1
    if task is not None:
        from app.tasks.in_the_loop import OrientationTrials

        if isinstance(task, OrientationTrials):
            views, robots = False, 0
    cfg = SessionConfig(scene=scene, views=views, audio=audio, audio_device=device, msaa=msaa, write_frames=0,
                        robots=robots)
    return VRSession(cfg, HeadlessBackend(width=size[0], height=size[1], realtime=realtime), task=task)


#: a pixel differing by more than this (0-255) shows another surface; less is the light interpolated over two
#: coplanar, overlapping copies of one wall (walls meeting end to end), whose depth tie pyrender breaks in its node
#: order, which follows Python's hash seed
FAR_LEVELS = 24
WARMUP = 15  # frames run before timing: shaders compiled, meshes and the texture atlas uploaded


def _timed(s, frames: int) -> dict:
    """Run ``WARMUP`` frames, then time ``frames`` more (fresh frame statistics)."""
    from app.vr.frame import FrameStats

    if s.views is not None:
        s.run(frames=WARMUP)
        s.stats = FrameStats(s.backend.target_hz)
    return s.run(frames=frames)


def _loop(scene, size, frames, **kw) -> tuple[dict, np.ndarray | None]:
    with _session(scene, size, **kw) as s:
        r = _timed(s, frames)
        return {k: r[k] for k in ("fps", "frame_ms_p50", "frame_ms_p99", "missed_frames")}, s.last_views


def _flat(scene, size, frames, **kw) -> tuple[dict, np.ndarray | None]:
    """The loop with the flat look (one colour per face, a directional light baked in; no textures, no baked room
    light, no cut faces): what the home's look costs. With ``kw`` (VisualScene's): another variant of the views."""
    from app.scene.visual import VisualScene

    with _session(scene, size) as s:
        s.views.close()
        s.views = VisualScene(s.scene, *size, robots=s.cfg.robots, msaa=False, **(kw or {"shading": "baked"}))
        r = _timed(s, frames)
        return {k: r[k] for k in ("fps", "frame_ms_p50", "frame_ms_p99")}, s.last_views


def _stock(scene, size, frames) -> dict:
    """Stock pyrender on the same loop: lit shader, 4x MSAA, colour and depth read back."""
    import pyrender

    from app.scene.visual import VisualScene
    from sonicverse_core.sensors.offscreen import keep_display_on_delete, release_offscreen

    with _session(scene, size) as s:
        s.views.close()
        s.views = v = VisualScene(s.scene, *size, shading="lit", robots=s.cfg.robots)
        release_offscreen(v.renderer)
        v.renderer = pyrender.OffscreenRenderer(*size)
        keep_display_on_delete(v.renderer)  # stock, but its deletion must not end the process's EGL display
        r = _timed(s, frames)
        return {k: r[k] for k in ("fps", "frame_ms_p50", "frame_ms_p99")}


def bench_vr(sizes, frames: int = 60, scene: str = "builtin:apartment", audio_seconds: float = 20.0,
             culling_scene: str = "builtin:apartment?seed=1", culling_levels=(0, 3), period: int = 256) -> dict:
    from sonicverse_core.progress import progress

    out = {"scene": scene, "frames": frames, "target_hz": 90.0, "sizes": {}}
    for w, h in progress(sizes, len(sizes), "view sizes"):
        fast, img_fast = _loop(scene, (w, h), frames)
        ms, img_ms = _loop(scene, (w, h), frames, msaa=True)  # same frames: the last views show the same pose
        stock = _stock(scene, (w, h), max(frames // 4, 8))
        flat, _ = _flat(scene, (w, h), frames)
        tri, _ = _flat(scene, (w, h), frames, shading="home", texture_filter="trilinear")
        out["sizes"][f"{w}x{h}"] = {
            "stereo_fps": fast["fps"], "frame_ms_p50": fast["frame_ms_p50"], "frame_ms_p99": fast["frame_ms_p99"],
            "msaa_fps": ms["fps"], "stock_pyrender_fps": stock["fps"], "flat_look_fps": flat["fps"],
            "home_look_cost_vs_flat": round(flat["fps"] / fast["fps"], 2) if fast["fps"] else None,
            "trilinear_fps": tri["fps"],
            "trilinear_cost": round(fast["fps"] / tri["fps"], 2) if tri["fps"] else None,
            "speedup_vs_stock": round(fast["fps"] / stock["fps"], 2) if stock["fps"] else None,
            "msaa_off_mean_abs_error": None if img_fast is None or img_ms is None else
            round(float(np.abs(img_fast.astype(np.int16) - img_ms).mean()), 3),
            "reaches_90hz": bool(fast["fps"] and fast["fps"] >= 90)}
    ao, _ = _loop(scene, (512, 512), frames * 4, views=False, audio="offline")
    out["audio_only_fps"] = ao["fps"]  # no views; binaural audio rendered by the frame clock
    out["device"] = _gl_renderer()
    out["room_culling"] = [room_culling(culling_scene, densify_levels=lv) for lv in culling_levels]
    if audio_seconds > 0:
        out["live_audio"] = _live_audio(scene, audio_seconds, period=period)
    return out


def densify(scene, levels: int) -> None:
    """Subdivide every mesh of a scene ``levels`` times (x4 triangles each): the procedural home standing in for a
    scanned house of as many triangles (same rooms, same pixels)."""
    from dataclasses import replace

    for _ in range(levels):
        for p in scene.static:
            p.mesh = p.mesh.subdivide()
        for o in scene.objects:
            o.mesh = o.mesh.subdivide()
            o.parts = tuple(replace(p, mesh=p.mesh.subdivide()) for p in o.parts)
    scene._static_mesh, scene._dynamic_cache, scene._world_cache = None, {}, {}


def room_culling(scene: str, size=(512, 512), poses: int = 40, reps: int = 3, seed: int = 0,
                 densify_levels: int = 0) -> dict:
    """Only the rooms a viewer may see loaded and drawn, against the whole scene, on the same poses (nav-grid points,
    random headings; every other door closed halfway through), alternating so that machine noise hits both:
    stereo ms per frame, triangles in the GL context, and the pixels that differ (a view missing a room would
    show the background where the whole scene shows a surface)."""
    from app.scene.eyes import IPD, eye_offsets
    from app.scene.visual import VisualScene, bake_lighting
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.sensors.camera import RenderScene, camera_matrix

    sc = load_scene(scene)
    rng = np.random.default_rng(seed)
    pts = NavGrid(sc).sample(rng, poses)
    densify(sc, densify_levels)
    heads = [(p[0], p[1], sc.floor_z + 1.6, float(rng.uniform(0, 360))) for p in pts]
    cull = VisualScene(sc, *size, cull_rooms=True, avatar=False)
    # the reference: the scene as one merged mesh (no culling), drawn by the same GL context (pyrender's EGL
    # platform cannot close two contexts in one process)
    whole = RenderScene(sc, face_shading=bake_lighting, look=cull.rs.look)
    cam = whole.scene.add(cull.camera, pose=np.eye(4))

    def render_whole(h):
        whole.sync()
        out = []
        for eye in eye_offsets(IPD):
            whole.scene.set_pose(cam, camera_matrix(*h) @ eye)
            out.append(cull.renderer.render(whole.scene, flags=cull._flags)[0])
        return np.stack(out)

    bg = np.round(np.array(cull.rs.scene.bg_color[:3]) * 255)
    diff_frac, far_frac, missing, tris, worst = [], [], 0, [], 0
    times = {"cull": [], "full": []}
    try:
        for k, h in enumerate(heads):
            if k == poses // 2:
                for d in sc.doors[::2]:
                    sc.set_door(d.name, 0.0)
            a, b = cull.render_stereo(h).astype(np.int16), render_whole(h).astype(np.int16)
            tris.append((cull.rs.drawn_triangles, cull.rs.loaded_triangles))
            d = np.abs(a - b).max(-1)
            diff_frac.append(float((d > 0).mean()))
            far_frac.append(float((d > FAR_LEVELS).mean()))
            worst = max(worst, int(d.max()))
            missing += int(((np.abs(a - bg).max(-1) <= 1) & (np.abs(b - bg).max(-1) > 1)).sum())
        for _ in range(reps):
            for name, render in (("cull", cull.render_stereo), ("full", render_whole)):
                t0 = time.perf_counter()
                for h in heads:
                    render(h)
                times[name].append((time.perf_counter() - t0) / len(heads) * 1000)
        total = whole.loaded_triangles
    finally:
        cull.close()
    ms_c, ms_f = float(np.median(times["cull"])), float(np.median(times["full"]))
    return {"scene": scene, "densified": densify_levels, "rooms": len(sc.rooms), "size": f"{size[0]}x{size[1]}",
            "poses": poses,
            "stereo_ms_culled": round(ms_c, 2), "stereo_ms_whole": round(ms_f, 2), "speedup": round(ms_f / ms_c, 3),
            "triangles_drawn_mean": round(float(np.mean([t[0] for t in tris])), 1),
            "triangles_loaded_mean": round(float(np.mean([t[1] for t in tris])), 1), "triangles_whole": int(total),
            "pixels_differing_mean": round(float(np.mean(diff_frac)), 6),
            "pixels_differing_max": round(float(np.max(diff_frac)), 6), "max_level_difference": worst,
            "pixels_differing_over_far_levels_max": round(float(np.max(far_frac)), 6),
            "background_where_whole_has_a_surface": missing}


def _gl_renderer() -> str:
    try:
        from OpenGL import GL

        from sonicverse_core.sensors.offscreen import offscreen_renderer, release_offscreen

        r = offscreen_renderer(16, 16)
        r._platform.make_current()
        name = GL.glGetString(GL.GL_RENDERER).decode()
        release_offscreen(r)
        return name
    except Exception as exc:  # noqa: BLE001
        return f"unknown ({exc})"


def live_audio_task(task: str, seconds: float = 60.0, scene: str = "builtin:apartment", agent: str | None = None,
                    seed: int = 0, period: int = 256) -> dict:
    """A human-robot task in the VR loop (headless backend, paced to the wall clock at 90 Hz, 512x512 stereo views
    unless the task is audio only) with the live pipeline on a private JACK dummy server for ``seconds``: xruns and
    callback timing while the task's agent (or participant) runs. The JACK dummy has no microphone: the robot hears
    the scene and silence where the user's voice would be. ``period``: the server's frames per cycle (the engine
    still renders 256-frame blocks, several per cycle)."""
    from app.tasks.in_the_loop import make_frame_task

    t = make_frame_task(task, agent, seed, trials=10_000)
    return {"task": t.name, "agent": getattr(t, "agent_name", "simulated"),
            **_live_audio(scene, seconds, task=t, realtime=True, period=period)}


def _check_stream(engine, tel: dict, seconds: float) -> int:
    """A window in which the stream was lost or stopped calling back is an error, not a run without xruns: the
    engine must still be running (a lost device or a dead worker is raised with the engine's news), the stream must
    still call back after the window, and it must have played at least 90% of the window's frames unless the audio
    server reported a late cycle in the window. A JACK dummy (or any timed) driver that wakes late does not catch
    up: it restarts its clock and the cycles it slept through are never run (jack2's ``JackTimedDriver``), so on a
    machine that starves it of the CPU the window holds fewer cycles than its length; each such cycle reaches the
    stream as an xrun, and the xrun count, not the frame count, is then the measurement (the JSON's ``frames`` and
    ``window_frames`` show what was lost). Returns the window's length in frames."""
    from app.audio_rt.worker import stall_seconds
    from sonicverse_core.errors import DeviceError

    def running() -> None:
        engine.poll()
        if engine.state != "running":
            news = engine.events[-1] if engine.events else "no news from the worker"
            raise DeviceError(f"the live stream is {engine.state} at the window's end ({news}): its xrun count "
                              f"would not be a measurement")

    running()
    if engine.wait_callbacks(1, timeout=stall_seconds(engine.cfg) + 0.5) < 1:
        running()  # the supervisor has most likely said so by now, with its news
        raise DeviceError("the live stream stopped calling back at the window's end: its xrun count would not be a "
                          "measurement")
    want = seconds * engine.cfg.sample_rate
    if tel["frames"] < 0.9 * want and tel["xrun_blocks"] == 0:
        raise DeviceError(f"the live stream played {tel['frames']} of the window's {int(want)} frames (engine "
                          f"{tel['state']}) and the audio server reported no late cycle: its xrun count would not "
                          f"be a measurement")
    return int(want)


def _live_audio(scene: str, seconds: float, task=None, realtime: bool = False, period: int = 256) -> dict:
    """The loop flat out at 512x512 stereo with the live pipeline on a JACK dummy server: xruns, callbacks."""
    from app.audio_rt.jack import JackServer, jack_buffer_size

    name = f"sv-bench-{os.getpid()}"
    old = os.environ.get("JACK_DEFAULT_SERVER")
    os.environ["JACK_DEFAULT_SERVER"] = name
    try:
        from app.audio_rt.loopback import PlatformProbe

        with JackServer(name, period=period) as srv, _session(scene, (512, 512), audio="live", device="system",
                                                       task=task, realtime=realtime) as s:
            served = jack_buffer_size()  # the server's frames per cycle, as it reports them
            s.frame()  # the loop is running (first poses handed over) and the JACK graph has settled: then count
            s.audio.engine.wait_settled()
            probe = PlatformProbe(seconds)  # its start stays out of the window; the loop runs on meanwhile
            while probe.due() > 0.02:
                s.frame()
            probe.wait_start()
            s.audio.engine.mark()
            s._last_in = None
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                s.frame()
            tel = s.audio.telemetry()
            window = _check_stream(s.audio.engine, tel, seconds)
            platform = probe.result({os.getpid(): "main", srv.proc.pid: "jackd", **s.audio.engine.threads()})
            platform["supervisor_scheduling"] = s.audio.engine.info.get("supervisor_scheduling")
            platform["callback_scheduling"] = tel["callback_scheduling"]
            platform["jack_scheduling"] = srv.scheduling
            platform.update(probe.attribute(tel["xrun_at_s"], tel["cycle_ms"], callback_ms=tel["xrun_callback_ms"],
                                            callback_cpu_ms=tel["xrun_callback_cpu_ms"]))
            r = s.summary()
        extra = {"task_summary": {k: v for k, v in r["task"].items() if k != "rows"}} if task is not None else {}
        return {**extra, "seconds": seconds, "jack_period": served, "loop_fps": r["fps"], "xruns": tel["xruns"],
                "frames": tel["frames"], "window_frames": window,
                "xrun_blocks": tel["xrun_blocks"], "cycle_blocks": tel["cycle_blocks"],
                "xrun_at_s": tel["xrun_at_s"], "xrun_callback_ms": tel["xrun_callback_ms"],
                "xrun_callback_cpu_ms": tel["xrun_callback_cpu_ms"],
                "callbacks": tel["callbacks"], "callback_ms": tel["callback_ms"],
                "callback_cpu_ms": tel["callback_cpu_ms"],
                "callback_errors": tel["callback_errors"], "pose_frames": tel["pose_frames"],
                "robot_blocks": tel["robot_blocks"], "platform": platform}
    finally:
        if old is None:
            os.environ.pop("JACK_DEFAULT_SERVER", None)
        else:
            os.environ["JACK_DEFAULT_SERVER"] = old
