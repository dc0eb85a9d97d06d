"""`sonicverse bench vr`: stereo frames per second of the headless loop, with references measured in the same run.

Per eye size: the loop as shipped (lighting baked into face colours, FLAT shader, single-sampled, no depth
read-back), the same with 4x MSAA (the error of leaving it out: mean absolute pixel difference, 0-255 levels), and
stock pyrender (lit PBR shader, 4x MSAA, colour + depth read-back) as the reference the speed-up is measured
against. Then the audio-only loop (tracking + binaural audio rendered by the frame clock), and the live audio pipeline (app/audio_rt on a private JACK dummy server) while
the loop renders 512x512 stereo flat out: xruns and callback timing.
"""
from __future__ import annotations

import os
import time

import numpy as np


def _session(scene: str, size, views=True, audio="none", msaa=False, device=None):
    from app.vr.headless import HeadlessBackend
    from app.vr.session import SessionConfig, VRSession

    cfg = SessionConfig(scene=scene, views=views, audio=audio, audio_device=device, msaa=msaa, write_frames=0)
    return VRSession(cfg, HeadlessBackend(width=size[0], height=size[1]))


def _loop(scene, size, frames, **kw) -> tuple[dict, np.ndarray | None]:
    with _session(scene, size, **kw) as s:
        r = s.run(frames=frames)
        return {k: r[k] for k in ("fps", "frame_ms_p50", "frame_ms_p99", "missed_frames")}, s.last_views


def _stock(scene, size, frames) -> dict:
    """Stock pyrender on the same loop: lit shader, 4x MSAA, colour and depth read back."""
    import pyrender

    from app.scene.visual import VisualScene

    with _session(scene, size) as s:
        s.views.close()
        s.views = v = VisualScene(s.scene, *size, shading="lit", robots=s.cfg.robots)
        v.renderer.delete()
        v.renderer = pyrender.OffscreenRenderer(*size)
        r = s.run(frames=frames)
        return {k: r[k] for k in ("fps", "frame_ms_p50", "frame_ms_p99")}


def bench_vr(sizes, frames: int = 60, scene: str = "builtin:apartment", audio_seconds: float = 20.0) -> dict:
    out = {"scene": scene, "frames": frames, "target_hz": 90.0, "sizes": {}}
    for w, h in sizes:
        fast, img_fast = _loop(scene, (w, h), frames)
        ms, img_ms = _loop(scene, (w, h), frames, msaa=True)  # same frames: the last views show the same pose
        stock = _stock(scene, (w, h), max(frames // 4, 8))
        out["sizes"][f"{w}x{h}"] = {
            "stereo_fps": fast["fps"], "frame_ms_p50": fast["frame_ms_p50"], "frame_ms_p99": fast["frame_ms_p99"],
            "msaa_fps": ms["fps"], "stock_pyrender_fps": stock["fps"],
            "speedup_vs_stock": round(fast["fps"] / stock["fps"], 2) if stock["fps"] else None,
            "msaa_off_mean_abs_error": None if img_fast is None or img_ms is None else
            round(float(np.abs(img_fast.astype(np.int16) - img_ms).mean()), 3),
            "reaches_90hz": bool(fast["fps"] and fast["fps"] >= 90)}
    ao, _ = _loop(scene, (512, 512), frames * 4, views=False, audio="offline")
    out["audio_only_fps"] = ao["fps"]  # no views; binaural audio rendered by the frame clock
    out["device"] = _gl_renderer()
    if audio_seconds > 0:
        out["live_audio"] = _live_audio(scene, audio_seconds)
    return out


def _gl_renderer() -> str:
    try:
        from OpenGL import GL

        import pyrender

        r = pyrender.OffscreenRenderer(16, 16)
        name = GL.glGetString(GL.GL_RENDERER).decode()
        r.delete()
        return name
    except Exception as exc:  # noqa: BLE001
        return f"unknown ({exc})"


def _live_audio(scene: str, seconds: float) -> dict:
    """The loop flat out at 512x512 stereo with the live pipeline on a JACK dummy server: xruns, callbacks."""
    from app.audio_rt.jack import JackServer

    name = f"sv-bench-{os.getpid()}"
    old = os.environ.get("JACK_DEFAULT_SERVER")
    os.environ["JACK_DEFAULT_SERVER"] = name
    try:
        with JackServer(name), _session(scene, (512, 512), audio="live", device="system") as s:
            s.audio.engine.mark()
            s._last_in = None
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                s.frame()
            tel = s.audio.telemetry()
            r = s.summary()
        return {"seconds": seconds, "loop_fps": r["fps"], "xruns": tel["xruns"], "callbacks": tel["callbacks"],
                "callback_ms": tel["callback_ms"], "callback_errors": tel["callback_errors"],
                "pose_frames": tel["pose_frames"]}
    finally:
        if old is None:
            os.environ.pop("JACK_DEFAULT_SERVER", None)
        else:
            os.environ["JACK_DEFAULT_SERVER"] = old
