"""`sonicverse bench cues`: does what the robot hears point where it should go?

Over AudioGoal episodes in train homes (the task's own sources, sounds and robot starts), the robot's ears stand at
the episode's start facing ``headings`` random ways; the goal's sound is rendered for ``seconds`` and the last
second is analysed, as an agent hears it in the middle of an episode. The reference direction is the source itself
where the ears see it (line of sight, Embree: nothing between but the sounding object's own parts), else the last bend of the shortest open path to it (the doorway or
corner it comes around: :func:`sonicverse_core.acoustics.paths.path_graph`), which is where a listener should hear
it from (issue 15) and where the agent should go.

Per case (line of sight or not) and per acoustic model, at places where the reference is to the side
(``|sin(bearing)| > 0.5``):

* ``ild_side``: the share whose interaural level difference (1.5 kHz up to Nyquist) has the reference's sign (left
  louder where it is on the left), and ``ild_corr``, its correlation with ``sin(bearing)`` over all places;
* ``itd_side``: the same for the interaural time difference (the peak of GCC-PHAT within 0.75 ms);
* ``onset_ild_side``, ``onset_itd_side``: the same from the frames just after the sound's onsets (20 ms frames whose
  energy rose by more than 3 dB, weighted by the rise: the precedence effect); ``onsets``: lateral places with any;
* ``level_vs_distance``: does louder mean nearer? The level at the ears (dB re the sound's own mean square, so a loud
  TV is not taken for a near one) against the geodesic distance to the goal over all places: the slope (dB/m), the
  correlation, and the median level within 3 m minus that beyond 6 m;
* ``path_share_db``: the median level of what the paths alone give (direct sound through
  walls + the paths; no reflections, no reverb) against the model's whole output: how far the late field drowns
  the direction.

Acoustic models, each rendered from the same places in the same run, with its cost (ms of compute per second of
audio, for one listener): ``paths`` (direct + transmission + paths: the direction's upper bound), ``paths+er``
(+ early reflections), ``whole-space`` (+ the late reverb of the whole connected space:
``BakeConfig(per_room=False)``, the default before session 27) and ``per-room`` (+ each room's own late reverb,
coupled: the default). Chance is 0.5.
"""
from __future__ import annotations

import math
import time

import numpy as np

MODELS = ("paths", "paths+er", "whole-space", "per-room")
SR = 16_000  # the envs' rate
MAX_ITD = 0.00075


def _ild(x: np.ndarray, sr: int, lo: float = 1500.0) -> float:
    """Left minus right level (dB) above ``lo`` Hz."""
    X = np.fft.rfft(x.astype(np.float64), axis=1)
    f = np.fft.rfftfreq(x.shape[1], 1 / sr)
    e = (np.abs(X[:, f >= lo]) ** 2).sum(1) + 1e-20
    return float(10 * np.log10(e[0] / e[1]))


def _itd(x: np.ndarray, sr: int) -> float:
    """Seconds by which the left ear leads (GCC-PHAT's peak within ``MAX_ITD``; > 0: the left leads)."""
    from agents.scripted import gcc_phat

    cc, e = gcc_phat(x, sr, MAX_ITD)
    if e <= 0:
        return float("nan")
    return (int(np.argmax(cc)) - len(cc) // 2) / sr


def _onset_cues(y: np.ndarray, sr: int, lo: float = 1500.0) -> tuple[float, float]:
    """(ITD s, ILD dB) weighted towards onsets, as the precedence effect hears them: the 20 ms frames (every 10 ms)
    of ``y`` (2, n; its first frame is the history) whose energy rose by more than 3 dB, each weighted by the rise
    (:func:`agents.scripted.onset_frames`). NaN without any onset."""
    from agents.scripted import frames_gcc_phat, onset_frames

    frame, hop = 320 * sr // 16000, 160 * sr // 16000
    fr, wt = onset_frames(y[:, frame:], y[:, :frame], frame, hop)
    cc, w = frames_gcc_phat(fr, wt, sr, MAX_ITD)
    if w <= 0:
        return float("nan"), float("nan")
    f = np.fft.rfftfreq(frame, 1 / sr)
    hi = (np.abs(np.fft.rfft(fr, axis=2)[:, :, f >= lo]) ** 2).sum(2)  # (2, frames)
    return (int(np.argmax(cc)) - len(cc) // 2) / sr, float(10 * np.log10(((wt * hi[0]).sum() + 1e-20) /
                                                                         ((wt * hi[1]).sum() + 1e-20)))


def _places(episodes: int, headings: int, seed: int):
    """(scene spec, scene, source position, sound signal, ears, [yaw...], geodesic distance to the goal) per episode
    of AudioGoal's train homes."""
    from sonicverse_core.tasks import make_env
    from sonicverse_core.tasks.base import sound_at

    env = make_env("AudioGoal", split="train", sensors=("pose",), reverb=False)
    rng = np.random.default_rng(seed)
    try:
        for _ in range(episodes):
            env.reset(seed=int(rng.integers(2**31)))
            u = env.unwrapped
            ep, scene = u.episode, u.home.scene
            yield (u.home.spec, scene, np.array(scene.object(ep.object_name).sound_position(), float),
                   sound_at(ep.sound, SR), np.array(u.home.world.ears, float),
                   [float(y) for y in rng.uniform(-180, 180, headings)], float(u.task.geo0))
    finally:
        env.close()


def bench_cues(episodes: int = 40, headings: int = 3, seconds: float = 2.0, seed: int = 0,
               models=MODELS) -> dict:
    from sonicverse_core.acoustics.config import RenderConfig
    from sonicverse_core.acoustics.occlusion import own_object_crossings, sounding_bounds
    from sonicverse_core.acoustics.paths import path_graph
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.geometry.raycast import SceneRayCaster

    bad = set(models) - set(MODELS)
    if bad:
        raise ConfigError(f"unknown model(s) {', '.join(sorted(bad))}; use {', '.join(MODELS)}")
    if not 1.0 < seconds <= 30.0:
        raise ConfigError(f"--seconds must be within 1-30 (the last second is analysed), got {seconds}")
    models = tuple(m for m in MODELS if m in models or m == "paths")  # paths: the reference level
    block = 400
    rows = []  # (model, los, sin(bearing), ild, itd, energy, level re the sound, geodesic m, onset itd, onset ild)
    cost = {m: 0.0 for m in models}
    bake_s = {"whole-space": 0.0, "per-room": 0.0}  # the probes' bakes (paths+er uses the whole space's)
    casters, probes = {}, {}
    n_places = 0
    for spec, scene, src, sig, ears, yaws, geo in _places(episodes, headings, seed):
        power = float(np.mean(sig.astype(np.float64) ** 2))  # the sound's own level: a loud TV is not a near one
        rc = casters.get(spec) or casters.setdefault(spec, SceneRayCaster(scene))
        cr = rc.crossings(src[None], ears[None])  # line of sight: nothing but the sounding object itself between
        los = bool(np.all(own_object_crossings(sounding_bounds(scene), rc.part_offset(), cr, src[None])))
        ref = src[:2]
        if not los:
            pr = path_graph(scene).path(src[:2], ears[:2])
            if pr is None:
                continue  # no open path: nowhere to point
            ref = pr.last
        d = ref - ears[:2]
        n_places += len(yaws)
        for m in models:
            key = (spec, "per-room" if m == "per-room" else "whole-space")
            if m != "paths" and key not in probes:  # (the early reflections come from the probes' rooms)
                t0 = time.perf_counter()
                probes[key] = scene_probes(scene, BakeConfig(per_room=m == "per-room"))
                bake_s[key[1]] += time.perf_counter() - t0
            cfg = RenderConfig(sample_rate=SR, block=block, early_reflections=m != "paths",
                               late_reverb=m in ("whole-space", "per-room"))
            r = AcousticRenderer(scene, cfg, probes.get(key))
            r.add_source(sig, position=src, loop=True)
            for y in yaws:
                r.add_listener(ears, yaw=y)
            t0 = time.perf_counter()
            outs = r.render(seconds)
            cost[m] += (time.perf_counter() - t0) / len(yaws)
            for y, o in zip(yaws, outs):
                x = o[:, -SR:]
                s = math.sin(math.atan2(d[1], d[0]) - math.radians(y))
                e = float(np.mean(x.astype(np.float64) ** 2))
                rows.append((m, los, s, _ild(x, SR), _itd(x, SR), e, 10 * math.log10(e / power + 1e-30), geo,
                             *_onset_cues(o[:, -SR - 320:], SR)))
    if not rows:
        raise ConfigError("no place had a source with a path to it: raise --episodes")
    return _summary(rows, models, cost, bake_s, n_places, seconds, episodes, headings, seed)


def _near_far(geo: np.ndarray, level: np.ndarray) -> float | None:
    """Median level (dB re the sound's own) of the places within 3 m of the goal (geodesic) minus that beyond 6 m."""
    near, far = level[geo < 3.0], level[geo > 6.0]
    return round(float(np.median(near) - np.median(far)), 2) if len(near) and len(far) else None


def _corr(x: np.ndarray, y: np.ndarray) -> float | None:
    """Pearson's correlation, or None where it is undefined (fewer than 3 places, or one side constant)."""
    if len(x) < 3 or np.std(x) == 0 or np.std(y) == 0:
        return None
    return round(float(np.corrcoef(x, y)[0, 1]), 3)


def _summary(rows, models, cost, bake_s, n_places, seconds, episodes, headings, seed) -> dict:
    out = {"bench": "cues", "task": "AudioGoal", "split": "train", "episodes": episodes, "headings": headings,
           "seconds": seconds, "seed": seed, "places": n_places, "sample_rate": SR, "models": {}}
    ref_e = {}
    for m, los, s, ild, itd, e, *_ in rows:
        if m == "paths":
            ref_e.setdefault(los, []).append(e)
    for m in models:
        res = {"render_ms_per_s": round(1000 * cost[m] / max(n_places, 1) / seconds, 2)}
        if bake_s.get(m):
            res["bake_s"] = round(bake_s[m], 2)  # the probes it needs, baked (or read from the cache) in this run
        lv = np.array([(r[6], r[7]) for r in rows if r[0] == m])  # (level, geodesic distance) per place, heading
        level, geo = lv[:, 0], lv[:, 1]
        slope = float(np.polyfit(geo, level, 1)[0]) if np.std(geo) > 0 else None
        res["level_vs_distance"] = {"db_per_m": None if slope is None else round(slope, 2),
                                    "corr": _corr(geo, level),
                                    "near_minus_far_db": _near_far(geo, level)}
        for los in (True, False):
            sel = [r for r in rows if r[0] == m and r[1] == los]
            if not sel:
                continue
            s = np.array([r[2] for r in sel])
            ild = np.array([r[3] for r in sel])
            itd = np.array([r[4] for r in sel])
            lat = np.abs(s) > 0.5
            ok = np.isfinite(itd)
            oitd = np.array([r[8] for r in sel])
            oild = np.array([r[9] for r in sel])
            on = np.isfinite(oitd) & lat
            case = {"places": len(sel), "lateral": int(lat.sum()),
                    "ild_side": round(float(np.mean(np.sign(ild[lat]) == np.sign(s[lat]))), 3) if lat.any() else None,
                    "itd_side": round(float(np.mean(np.sign(itd[lat & ok]) == np.sign(s[lat & ok]))), 3)
                    if (lat & ok).any() else None,
                    "ild_corr": _corr(s, ild), "itd_corr": _corr(s[ok], itd[ok]),
                    "onsets": int(on.sum()),
                    "onset_ild_side": round(float(np.mean(np.sign(oild[on]) == np.sign(s[on]))), 3) if on.any() else None,
                    "onset_itd_side": round(float(np.mean(np.sign(oitd[on]) == np.sign(s[on]))), 3) if on.any() else None}
            if m != "paths":
                e = np.array([r[5] for r in sel])
                pe = np.array(ref_e[los])
                case["path_share_db"] = round(float(np.median(10 * np.log10((pe + 1e-30) / (e + 1e-30)))), 2)
            res["line_of_sight" if los else "no_line_of_sight"] = case
        out["models"][m] = res
    return out
