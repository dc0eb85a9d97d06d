"""Auditory orientation training (audio only: no renderer for the eyes is loaded).

Trials in blocks. In a *turn* trial a sound plays from a place around the participant (azimuth all round,
elevation -20 to +40 degrees, 1.5-3 m away, rendered binaurally in a virtual room with the acoustic engine); the
participant turns to face it and presses the trigger: azimuth error, elevation error, front-back reversal, response
time. In a *walk* trial the sound keeps playing and the participant walks to it: success within 0.5 m, path
efficiency (straight distance / walked distance), time to target. After each trial a feedback sound tells right
(within ``correct_deg`` of the target, no reversal) from wrong. An adaptive staircase (Levitt's transformed up-down,
1-up-2-down by default, converging on 70.7% correct; one track per trial kind) sets the difficulty: the sound's duration (shorter is harder),
the reverberation (more is harder) or a distractor's level (louder is harder); its threshold is the mean of the last
even number of reversals (geometric mean for ratio-scaled parameters).

Front-back reversals are scored in the usual way: a response in the other front/back hemifield than the target,
for targets more than 15 degrees off the interaural axis (near the axis front and back are the same place); the
azimuth error "after resolving reversals" mirrors a reversed response back across the interaural axis first.

The participant is a person (``sonicverse vr --task orientation-training``) or :class:`SimulatedListener`: a
listener model with a chosen localisation noise (degrees, Gaussian), front-back confusion probability and learning
rate, so the whole task, its staircase and its metrics are testable end to end. For that model the expected mean
absolute azimuth error after resolving reversals is ``noise * sqrt(2 / pi)`` (7.98 degrees for 10) and the
reversal rate its confusion probability (tested over 1,000 trials).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from sonicverse_core.errors import ConfigError

AXIS_EXCLUSION_DEG = 15.0
DIFFICULTIES = ("duration", "reverb", "distractor")


def wrap(a):
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


def mirror(az):
    """The azimuth mirrored across the interaural axis (front <-> back): 180 - az."""
    return wrap(180.0 - np.asarray(az, float))


def score_turn(target_az: float, response_az: float) -> tuple[float, bool]:
    """(absolute azimuth error after resolving a reversal, reversed?)."""
    eligible = abs(math.cos(math.radians(target_az))) > math.sin(math.radians(AXIS_EXCLUSION_DEG))
    reversed_ = eligible and (math.cos(math.radians(target_az)) * math.cos(math.radians(response_az)) < 0)
    r = float(mirror(response_az)) if reversed_ else response_az
    return abs(float(wrap(r - target_az))), bool(reversed_)


@dataclass(frozen=True)
class OrientationConfig:
    mode: str = "turn"  # turn | walk | mixed (blocks alternate)
    trials: int = 40  # per block
    blocks: int = 1
    practice: int = 0  # practice trials before the first block (not scored)
    room: str = "shoebox:6x5x3"  # the virtual room (scene spec)
    sample_rate: int = 16000
    elevation: tuple = (-20.0, 40.0)
    distance: tuple = (1.5, 3.0)
    head_height: float = 1.6
    sounds: str = "heard"
    difficulty: str = "duration"  # duration | reverb | distractor
    staircase: str = "1up2down"  # 1up2down | 1up3down | none
    start_level: float | None = None  # default per difficulty
    correct_deg: float = 20.0
    feedback: bool = True
    walk_radius: float = 0.5
    walk_timeout: float = 20.0
    render: bool = True  # render each stimulus binaurally (what a person hears; the model is told the truth)
    hrtf: bool = True  # False: an interaural time and level panner (no spectral or front-back cues)
    reverb: bool = True  # False: the room's reflections and reverb are left out

    def __post_init__(self):
        if self.mode not in ("turn", "walk", "mixed"):
            raise ConfigError(f"mode must be turn, walk or mixed, got '{self.mode}'")
        if self.difficulty not in DIFFICULTIES:
            raise ConfigError(f"difficulty must be one of {', '.join(DIFFICULTIES)}, got '{self.difficulty}'")
        if self.staircase not in ("1up2down", "1up3down", "none"):
            raise ConfigError(f"staircase must be 1up2down, 1up3down or none, got '{self.staircase}'")
        if self.trials < 1 or self.blocks < 1 or self.practice < 0:
            raise ConfigError("need trials >= 1 and blocks >= 1 (practice >= 0)")
        if not (0 < self.distance[0] <= self.distance[1] <= 20):
            raise ConfigError(f"distance must be an ordered range within 0-20 m, got {self.distance}")


#: per difficulty: (start level, step factor, lower bound, upper bound, harder = lower?)
LEVELS = {"duration": (1.0, 0.7, 0.02, 2.0, True),  # seconds of sound
          "reverb": (0.2, 1.4, 0.1, 3.0, False),  # RT60 of the room (s)
          "distractor": (0.05, 1.4, 0.01, 2.0, False)}  # distractor amplitude relative to the target


class Staircase:
    """Levitt's transformed up-down staircase on a ratio scale: ``down`` correct in a row make it harder (level
    times ``factor`` towards hard), one wrong makes it easier. Threshold: geometric mean of the last even number of
    reversal levels (at most 6)."""

    def __init__(self, start: float, factor: float, lo: float, hi: float, harder_is_lower: bool, down: int = 2):
        if not (lo <= start <= hi and factor > 0 and factor != 1 and down >= 1):
            raise ConfigError("staircase needs lo <= start <= hi, a factor other than 1 and down >= 1")
        self.level, self.lo, self.hi, self.down = float(start), lo, hi, down
        self.step = factor if harder_is_lower == (factor < 1) else 1.0 / factor  # multiply to make it harder
        self.run = 0
        self.direction = 0  # +1 harder, -1 easier
        self.reversals: list[float] = []
        self.history: list[float] = []

    def update(self, correct: bool) -> float:
        self.history.append(self.level)
        move = 0
        if correct:
            self.run += 1
            if self.run >= self.down:
                move, self.run = 1, 0
        else:
            move, self.run = -1, 0
        if move:
            if self.direction and move != self.direction:
                self.reversals.append(self.level)
            self.direction = move
            f = self.step if move > 0 else 1.0 / self.step
            self.level = float(min(max(self.level * f, self.lo), self.hi))
        return self.level

    @property
    def threshold(self) -> float | None:
        r = self.reversals[-6:]
        if len(r) % 2:
            r = r[1:]
        return float(np.exp(np.mean(np.log(r)))) if r else None


class FixedLevel(Staircase):
    def __init__(self, level: float):
        self.level, self.reversals, self.history = float(level), [], []

    def update(self, correct: bool) -> float:
        self.history.append(self.level)
        return self.level


@dataclass(frozen=True)
class SimulatedListener:
    """A listener model. Perceived azimuth = the target's, mirrored across the interaural axis with probability
    ``front_back`` (a front-back confusion), plus Gaussian noise of ``noise_deg`` (elevation: ``elevation_noise_deg``).
    Noise and confusions shrink with practice: both are scaled by ``exp(-learning_rate * trial)``, down to
    ``floor`` of their start. Harder trials add noise: a sound shorter than ``full_duration`` s scales it by
    ``full_duration / duration``; reverberation by ``1 + rt60``-0.2 beyond 0.2 s; a distractor by ``1 + level``.
    Walking: ``walk_speed`` m/s, a fresh estimate of the direction every ``update_s`` s."""

    noise_deg: float = 10.0
    elevation_noise_deg: float = 12.0
    front_back: float = 0.1
    learning_rate: float = 0.0
    floor: float = 0.3
    full_duration: float = 0.25
    response_time: tuple = (1.2, 0.25)  # lognormal: median s, sigma of the log
    walk_speed: float = 1.0
    update_s: float = 0.5

    def __post_init__(self):
        if not (0 <= self.noise_deg <= 180 and 0 <= self.elevation_noise_deg <= 90):
            raise ConfigError("localisation noise must be within 0-180 degrees (elevation 0-90)")
        if not (0 <= self.front_back <= 1 and self.learning_rate >= 0 and 0 < self.floor <= 1):
            raise ConfigError("front_back must be a probability, learning_rate >= 0, floor in (0, 1]")

    def _scale(self, trial: int, difficulty: str, level: float) -> tuple[float, float]:
        learn = max(self.floor, math.exp(-self.learning_rate * trial))
        hard = 1.0
        if difficulty == "duration":
            hard = max(1.0, self.full_duration / max(level, 1e-3))
        elif difficulty == "reverb":
            hard = 1.0 + max(0.0, level - 0.2)
        elif difficulty == "distractor":
            hard = 1.0 + level
        return learn * hard, learn

    def perceive(self, az: float, el: float, trial: int, difficulty: str, level: float,
                 rng: np.random.Generator, confused: bool | None = None) -> tuple[float, float]:
        k, learn = self._scale(trial, difficulty, level)
        if confused is None:
            confused = rng.random() < self.front_back * learn
        a = float(mirror(az)) if confused else az
        return (float(wrap(a + rng.normal(0.0, self.noise_deg * k))),
                float(np.clip(el + rng.normal(0.0, self.elevation_noise_deg * k), -90, 90)))

    def turn(self, az, el, trial, difficulty, level, rng) -> tuple[float, float, float]:
        """(response azimuth, response elevation, response time s)."""
        ra, re = self.perceive(az, el, trial, difficulty, level, rng)
        med, s = self.response_time
        return ra, re, float(med * math.exp(rng.normal(0.0, s)))

    def walk(self, start, source, radius, timeout, trial, difficulty, level, rng) -> dict:
        """Walk to the sound: ``start`` and ``source`` (x, y); returns the path and the outcome."""
        k, learn = self._scale(trial, difficulty, level)
        confused = rng.random() < self.front_back * learn  # one confusion per trial, corrected on the way
        p = np.asarray(start, float).copy()
        src = np.asarray(source, float)
        heading = 0.0  # faces +x at the start
        path, t, walked = [p.copy()], 0.0, 0.0
        reached_at = None
        while t < timeout:
            v = src - p
            d = float(np.hypot(*v))
            if d <= radius:
                reached_at = t
                break
            az = math.degrees(math.atan2(v[1], v[0])) - heading  # relative to the head
            if confused and d < float(np.hypot(*(src - path[0]))) * 0.5:
                confused = False  # close to it the mistake becomes obvious
            pa, _ = self.perceive(az, 0.0, trial, difficulty, level, rng, confused=confused)
            heading = heading + pa
            step = min(self.walk_speed * self.update_s, max(d - 0.8 * radius, 0.05))
            p = p + step * np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading))])
            walked += step
            t += self.update_s
            path.append(p.copy())
        straight = max(float(np.hypot(*(src - np.asarray(start)))) - radius, 1e-9)
        ok = reached_at is not None
        return {"success": ok, "time_to_target_s": reached_at if ok else None,
                "path_efficiency": min(1.0, straight / walked) if ok and walked > 0 else None,
                "walked_m": walked, "path": np.array(path)}


def feedback_sound(correct: bool, sample_rate: int) -> np.ndarray:
    """A short rising chime (right) or a low buzz (wrong), mono float32 at -12 dBFS peak."""
    t = np.arange(int(0.25 * sample_rate)) / sample_rate
    env = np.minimum(1.0, t / 0.01) * np.exp(-t / 0.08)
    if correct:
        x = np.sin(2 * np.pi * 880 * t) + np.sin(2 * np.pi * 1320 * t) * (t > 0.08)
    else:
        x = np.sign(np.sin(2 * np.pi * 150 * t)) * 0.6
    return (0.25 * env * x / max(np.abs(x).max(), 1e-9)).astype(np.float32)


class OrientationTraining:
    """Runs a session of trials. ``run(participant, rng)`` -> list of trial rows (dicts); the participant is a
    :class:`SimulatedListener` (a person answers through the VR frame task instead)."""

    def __init__(self, config: OrientationConfig | None = None, **kwargs):
        self.cfg = config or OrientationConfig(**kwargs)
        c = self.cfg
        start, factor, lo, hi, harder_low = LEVELS[c.difficulty]
        s0 = c.start_level if c.start_level is not None else start

        def make():
            if c.staircase == "none":
                return FixedLevel(s0)
            return Staircase(s0, factor, lo, hi, harder_low, down=2 if c.staircase == "1up2down" else 3)

        # one track per trial kind: facing a sound and walking to it are not equally hard at the same level
        self.staircases = {m: make() for m in dict.fromkeys(self.modes())}
        self._scene = None
        self._probes = None

    # --- stimuli ----------------------------------------------------------------------------------------------
    def stimulus(self, rng: np.random.Generator) -> dict:
        c = self.cfg
        from assets_manifest.soundbank import CATEGORIES, HEARD, UNHEARD

        cat = CATEGORIES[int(rng.integers(len(CATEGORIES)))]
        variants = HEARD if c.sounds == "heard" else UNHEARD
        return {"sound": f"{cat}/{int(variants[int(rng.integers(len(variants)))])}",
                "azimuth": float(rng.uniform(-180.0, 180.0)), "elevation": float(rng.uniform(*c.elevation)),
                "distance": float(rng.uniform(*c.distance))}

    def _room(self):
        if self._scene is None:
            from sonicverse_core.acoustics.probes import scene_probes
            from sonicverse_core.scene.spec import load_scene

            self._scene = load_scene(self.cfg.room)
            self._probes = scene_probes(self._scene)
        return self._scene

    def listener_position(self) -> np.ndarray:
        s = self._room()
        lo, hi = s.bounds
        c = (lo + hi) / 2
        return np.array([c[0], c[1], s.floor_z + self.cfg.head_height])

    def render(self, stim: dict, level: float) -> np.ndarray:
        """The binaural stimulus (2, n) as the participant hears it, facing +x at the room's centre."""
        from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
        from sonicverse_core.tasks.base import sound_at

        c = self.cfg
        scene = self._room()
        rc = RenderConfig(sample_rate=c.sample_rate, block=512, output="binaural" if c.hrtf else "stereo",
                          early_reflections=c.reverb, late_reverb=c.reverb)
        r = AcousticRenderer(scene, rc, self._probes)
        head = self.listener_position()
        dur = level if c.difficulty == "duration" else 1.0
        x = sound_at(stim["sound"], c.sample_rate)
        n = max(int(dur * c.sample_rate), 64)
        sig = np.resize(x, n).astype(np.float32)
        ramp = min(int(0.005 * c.sample_rate), n // 2)
        sig[:ramp] *= np.linspace(0, 1, ramp, dtype=np.float32)
        sig[-ramp:] *= np.linspace(1, 0, ramp, dtype=np.float32)
        sig = np.concatenate([sig, np.zeros(int(0.3 * c.sample_rate), np.float32)])
        a, e = math.radians(stim["azimuth"]), math.radians(stim["elevation"])
        d = stim["distance"]
        pos = head + d * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
        lo, hi = scene.bounds
        pos = np.clip(pos, lo + 0.1, hi - 0.1)
        r.add_source(sig, position=pos, loop=False)
        if c.difficulty == "distractor":
            da = a + math.radians(float(stim.get("distractor_offset", 90.0)))
            dpos = np.clip(head + 2.0 * np.array([math.cos(da), math.sin(da), 0.0]), lo + 0.1, hi - 0.1)
            r.add_source(np.resize(sound_at("sofa/0", c.sample_rate), len(sig)), position=dpos, loop=False,
                         gain=level)
        r.add_listener(head, yaw=0.0)
        blocks = int(math.ceil(len(sig) / rc.block))
        return np.concatenate([r.render_block()[0] for _ in range(blocks)], axis=1)

    # --- a session --------------------------------------------------------------------------------------------
    def modes(self) -> list[str]:
        c = self.cfg
        if c.mode != "mixed":
            return [c.mode] * c.blocks
        return ["turn" if b % 2 == 0 else "walk" for b in range(c.blocks)]

    def plan(self) -> list[tuple]:
        """The session's trials in order: (block, mode), block ``"practice"`` for the practice trials."""
        c = self.cfg
        plan = [("practice", self.modes()[0])] * c.practice
        for b, mode in enumerate(self.modes()):
            plan += [(b, mode)] * c.trials
        return plan

    def run(self, participant: SimulatedListener, rng: np.random.Generator, on_trial=None) -> list[dict]:
        rows: list[dict] = []
        scored = 0
        for i, (block, mode) in enumerate(self.plan()):
            row = self.run_trial(i, block, mode, participant, rng, scored)
            scored += block != "practice"
            rows.append(row)
            if on_trial:
                on_trial(i, row)
        return rows

    def run_trial(self, i: int, block, mode: str, participant: SimulatedListener, rng: np.random.Generator,
                  scored: int) -> dict:
        """One trial (its stimulus drawn from ``rng``) at the staircase's level for ``mode``; ``scored``: the scored
        trials before it (the listener model's practice). Updates the staircase unless it is a practice trial."""
        c = self.cfg
        stim = self.stimulus(rng)
        stair = self.staircases[mode]
        level = stair.level
        row = {"trial": i, "block": block, "mode": mode, "practice": block == "practice",
               "difficulty": c.difficulty, "level": level, **stim}
        if c.render:
            audio = self.render(stim, level)
            row["stimulus_itd_us"] = _itd_us(audio, c.sample_rate)
            row["stimulus_ild_db"] = _ild_db(audio)
        if mode == "turn":
            ra, re, rt = participant.turn(stim["azimuth"], stim["elevation"], scored, c.difficulty, level, rng)
            err, rev = score_turn(stim["azimuth"], ra)
            correct = err <= c.correct_deg and not rev
            row.update(response_azimuth=ra, response_elevation=re, response_time_s=rt, azimuth_error_deg=err,
                       elevation_error_deg=abs(re - stim["elevation"]), reversal=rev,
                       reversal_eligible=abs(math.cos(math.radians(stim["azimuth"])))
                       > math.sin(math.radians(AXIS_EXCLUSION_DEG)))
        else:
            a = math.radians(stim["azimuth"])
            src = stim["distance"] * np.array([math.cos(a), math.sin(a)])
            w = participant.walk((0.0, 0.0), src, c.walk_radius, c.walk_timeout, scored, c.difficulty, level, rng)
            correct = bool(w["success"])
            row.update(walk_success=w["success"], path_efficiency=w["path_efficiency"],
                       time_to_target_s=w["time_to_target_s"], walked_m=w["walked_m"])
        row["correct"] = bool(correct)
        row["feedback"] = ("right" if correct else "wrong") if c.feedback else ""
        if block != "practice":
            stair.update(correct)
        return row

    def summary(self, rows: list[dict]) -> dict:
        from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95

        rows = [r for r in rows if not r["practice"]]
        turn = [r for r in rows if r["mode"] == "turn"]
        walk = [r for r in rows if r["mode"] == "walk"]
        ok = [r for r in walk if r["walk_success"]]
        return {"azimuth_error_deg": mean_ci95(r["azimuth_error_deg"] for r in turn),
                "elevation_error_deg": mean_ci95(r["elevation_error_deg"] for r in turn),
                "front_back_confusion_rate": rate_ci95(r["reversal"] for r in turn if r["reversal_eligible"]),
                "response_time_s": mean_ci95(r["response_time_s"] for r in turn),
                "walk_success": rate_ci95(r["walk_success"] for r in walk),
                "path_efficiency": mean_ci95(r["path_efficiency"] for r in ok),
                "time_to_target_s": mean_ci95(r["time_to_target_s"] for r in ok),
                "trials": len(rows),
                "staircase": {m: {"difficulty": self.cfg.difficulty, "threshold": st.threshold,
                                  "reversals": len(st.reversals)} for m, st in self.staircases.items()},
                "config": asdict(self.cfg)}


def _itd_us(audio: np.ndarray, sr: int) -> float:
    """Interaural delay of a binaural signal (microseconds, left ear leading > 0): GCC-PHAT over the first 20 ms
    after the sound's onset (the direct sound, before the room's reflections arrive: the precedence effect)."""
    x = audio.astype(float)
    mag = np.abs(x).max(axis=0)
    on = int(np.argmax(mag > 0.1 * max(mag.max(), 1e-12)))
    a, b = max(on - int(0.002 * sr), 0), on + int(0.02 * sr)
    l, r = x[0, a:b], x[1, a:b]
    n = len(l)
    lag = int(0.001 * sr)
    X = np.fft.rfft(r, 2 * n) * np.conj(np.fft.rfft(l, 2 * n))
    cc = np.fft.irfft(X / (np.abs(X) + 1e-12), 2 * n)
    cc = np.concatenate([cc[-lag:], cc[:lag + 1]])
    return float((int(np.argmax(cc)) - lag) / sr * 1e6)


def _ild_db(audio: np.ndarray) -> float:
    """Interaural level difference (dB, left louder > 0)."""
    e = np.mean(audio.astype(float) ** 2, axis=1) + 1e-20
    return float(10 * np.log10(e[0] / e[1]))


def learning_curve(rows: list[dict], out) -> None:
    """A PNG of the per-trial error (turn: azimuth error; walk: time to target) and the staircase level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if not r["practice"]]
    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    turn = [(r["trial"], r["azimuth_error_deg"]) for r in rows if r["mode"] == "turn"]
    if turn:
        t, e = np.array(turn).T
        ax[0].plot(t, e, ".", alpha=0.5, label="azimuth error (after resolving reversals)")
        k = min(20, len(e))
        ax[0].plot(t[k - 1:], np.convolve(e, np.ones(k) / k, mode="valid"), "-", label=f"running mean of {k}")
        ax[0].set_ylabel("error (deg)")
    walk = [(r["trial"], r["time_to_target_s"]) for r in rows if r["mode"] == "walk" and r["walk_success"]]
    if walk:
        t, e = np.array(walk, float).T
        ax[0].plot(t, e, "x", label="time to target (s)")
    ax[0].legend(loc="upper right")
    ax[1].plot([r["trial"] for r in rows], [r["level"] for r in rows], "-o", ms=3)
    ax[1].set_ylabel(rows[0]["difficulty"] if rows else "level")
    ax[1].set_xlabel("trial")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
