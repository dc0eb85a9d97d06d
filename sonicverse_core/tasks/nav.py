"""The three navigation tasks, run by the generic :class:`~sonicverse_core.tasks.base.TaskEnv`.

``Sonicverse/AudioGoal-v0``: go to the sounding object (depth + binaural audio); the episode succeeds as soon as
the robot is within 0.36 m of one of the terminal positions (up to nine, the object in sight from each). Its sound
plays all episode, looped, as SoundSpaces' AudioNav does (``AUDIO.EVERLASTING``); ``everlasting=False`` stops it
after ``sound_seconds``.
``Sonicverse/AudioPointGoal-v0``: the same with a GPS + compass pointer to the goal.
``Sonicverse/SemanticAudioNav-v0``: the paper's task: RGB + depth + audio; the sound stops after ``sound_seconds``
(4-20 s by default); a third action component > 0 is the stop signal, and only a stop within 0.36 m of a terminal
position succeeds.

Reward: geodesic progress (m) + ``success_reward`` on success - ``step_penalty`` per step - ``collision_penalty``
per step with a bump. Privileged state (``env.unwrapped.privileged()``): ``world``, ``goals`` (k <= 9, 2),
``at_goal`` (within 0.36 m of a terminal position now).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from gymnasium import spaces

from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.base import Task, TaskConfig, TaskEnv, sound_at
from sonicverse_core.tasks.episodes import SOUND_SECONDS, SUCCESS_RADIUS, Episode, sample_episode
from sonicverse_core.tasks.metrics import shortest_actions, sna, soft_spl, spl

__all__ = ["AudioGoal", "AudioPointGoal", "SemanticAudioNav", "NavTask", "TaskConfig", "TaskEnv"]


class NavTask(Task):
    name = "AudioGoal"
    episode_type = Episode
    everlasting = True  # the goal's sound plays all episode (an episode's ``sound_seconds`` is then inf)

    def __init__(self, cfg: TaskConfig, **options):
        super().__init__(cfg, **options)
        if cfg.everlasting is not None:
            self.everlasting = cfg.everlasting
        if self.everlasting and tuple(cfg.sound_seconds) != tuple(SOUND_SECONDS):
            raise ConfigError(f"{self.name}'s sound plays all episode, so sound_seconds has no effect: pass "
                              "everlasting=False to stop it after sound_seconds")

    def sample_episode(self, env, rng: np.random.Generator) -> Episode:
        c = self.cfg
        for _ in range(50):
            spec = env.scene_specs[int(rng.integers(len(env.scene_specs)))]
            home = env.use_home(spec)
            ep = sample_episode(home.world, spec, c.split, c.sounds, rng, episode_id="",
                                geodesic_range=c.geodesic_range, sound_seconds=c.sound_seconds)
            if ep is not None:
                lo, hi = c.source_gain
                gain = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else float(lo)
                # the duration is drawn either way, so episodes are the same with and without an everlasting sound
                secs = math.inf if self.everlasting else ep.sound_seconds
                return replace(ep, source_gain=gain, sound_seconds=secs)
        raise ConfigError("no valid episode could be sampled in these homes (geodesic range too strict?)")

    def reset(self, env, rng, options):
        ep = self.episode(env, rng, options)
        home = env.use_home(ep.scene)
        world = home.world
        world.place_robot(*ep.start)
        self.goals = np.array(ep.goals, float)
        self._field = world.grid.distance_field(self.goals)
        env.new_renderer()
        base = sound_at(ep.sound, self.cfg.sample_rate)
        if math.isinf(ep.sound_seconds):  # everlasting: looped all episode
            env.source = env.add_sound(base, loop=True, gain=ep.source_gain, attached_to=ep.object_name)
        else:
            n = int(ep.sound_seconds * self.cfg.sample_rate)
            sig = np.resize(base, n) if n > 0 else base[:1] * 0
            env.source = env.add_sound(sig, loop=False, gain=ep.source_gain, attached_to=ep.object_name)
        self.geo0 = self.prev_geo = self._geodesic(env)
        return ep

    def _geodesic(self, env) -> float:
        w = env.home.world
        return float(w.grid.geodesic_from_field(self._field, w.pose[None, :2])[0])

    def at_goal(self, env) -> bool:
        d = np.linalg.norm(self.goals - env.home.world.pose[:2], axis=1)
        return float(np.min(d)) <= SUCCESS_RADIUS

    def evaluate(self, env, a):
        geo = self._geodesic(env)
        reached = self.at_goal(env)
        stop = bool(self.stop_action and a[2] > 0)
        success = reached and (stop or not self.stop_action)
        c = self.cfg
        reward = (self.prev_geo - geo if np.isfinite(geo) and np.isfinite(self.prev_geo) else 0.0)
        reward += c.success_reward * success - c.step_penalty - c.collision_penalty * env.home.world.bumped
        self.prev_geo = geo
        return reward, success or stop, success

    def info(self, env) -> dict:
        return {"distance_to_goal": self.prev_geo}

    def metrics(self, env, success: bool) -> dict:
        l, p = self.geo0, env.path_length
        n_star = shortest_actions(l, env.robot.max_speed, self.cfg.step_seconds)
        return {"success": float(success), "spl": spl(success, l, p), "sna": sna(success, n_star, env.steps),
                "soft_spl": soft_spl(l, p, self.prev_geo), "distance_to_goal": self.prev_geo, "geodesic": l,
                "path_length": p, "steps": env.steps, "n_star": n_star, "collisions": env.collisions}

    def observation_spaces(self, env) -> dict:
        if "pointgoal" not in env.sensors:
            return {}
        return {"pointgoal": spaces.Box(-1000.0, 1000.0, (3,), np.float32)}

    def observe(self, env, obs) -> None:
        if "pointgoal" not in env.sensors:
            return
        w, pose = env.home.world, env.sensed_pose
        g = self.goals[int(np.argmin(np.linalg.norm(self.goals - w.pose[:2], axis=1)))]
        d = g - pose[:2]
        bearing = math.atan2(d[1], d[0]) - math.radians(pose[2])
        obs["pointgoal"] = np.array([math.hypot(*d), math.cos(bearing), math.sin(bearing)], np.float32)

    def privileged(self, env) -> dict:
        return {"world": env.home.world, "goals": self.goals.copy(), "at_goal": self.at_goal(env)}


class AudioGoal(NavTask):
    name = "AudioGoal"


class AudioPointGoal(NavTask):
    name = "AudioPointGoal"
    default_sensors = ("depth", "audio", "spectrogram", "bump", "pose", "pointgoal")


class SemanticAudioNav(NavTask):
    name = "SemanticAudioNav"
    default_sensors = ("rgb", "depth", "audio", "spectrogram", "bump", "pose")
    stop_action = True
    everlasting = False
