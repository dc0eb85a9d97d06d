"""The study file (TOML), validated when read: every mistake is one :class:`StudyError` line naming the key.

```toml
name = "orientation-hrtf"          # letters, digits, - and _
seed = 7                           # every trial's seed derives from it, the participant and the session
counterbalance = "latin"           # latin (balanced Latin square by enrolment index) | least-filled
break_s = 30                       # a break between blocks (0: none); headless runs log it and go on

[quality]                          # a trial beyond any of these is flagged at the end of the session
missed_frames = 5
xruns = 0
latency_ms = 40

[simulated_participant]            # the listener model of headless runs (SimulatedListener's fields)
noise_deg = 10.0
front_back = 0.1

[conditions.hrtf]                  # conditions, in the order the Latin square numbers them
hrtf = "on"                        # on | off (off: an interaural time and level panner)
reverb = "on"                      # on | off
[conditions.panner]
hrtf = "off"
simulated = { front_back = 0.35 }  # what the condition does to the simulated participant (headless runs)

[[blocks]]
name = "orientation"
task = "orientation-training"      # a task of the registry (`sonicverse task list`)
trials = 4
time_limit_s = 30                  # a trial's limit: a person's in the VR app (default 60 s), a robot task's
                                   # episode headless too (default: the task's limit)
practice = 1                       # practice trials before the block (recorded, flagged practice)
mode = "turn"                      # orientation training: turn | walk
per_condition = true               # one block per condition, in the participant's order
[[blocks]]
name = "following"
task = "speaker-following"
trials = 2
agent = "scripted"                 # the robot's agent (robot tasks)
condition = "hrtf"                 # a block in one fixed condition
```
"""
from __future__ import annotations

import hashlib
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from sonicverse_core.errors import StudyError

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")
LISTENER_KEYS = ("noise_deg", "elevation_noise_deg", "front_back", "learning_rate", "floor", "walk_speed")


@dataclass(frozen=True)
class Condition:
    name: str
    hrtf: bool = True
    reverb: bool = True
    agent: str | None = None  # the robot's agent (robot tasks), else the block's
    home: str | None = None  # a scene spec for robot tasks, else the test homes
    simulated: dict = field(default_factory=dict)  # SimulatedListener overrides (headless runs)

    def as_dict(self) -> dict:
        return {"name": self.name, "hrtf": "on" if self.hrtf else "off", "reverb": "on" if self.reverb else "off",
                "agent": self.agent, "home": self.home, "simulated": dict(self.simulated)}


@dataclass(frozen=True)
class Block:
    name: str
    task: str  # the registry's command-line name
    trials: int
    practice: int = 0
    per_condition: bool = True
    condition: str | None = None  # fixed condition when not per_condition
    agent: str | None = None
    mode: str = "turn"
    difficulty: str = "duration"
    staircase: str = "1up2down"
    time_limit_s: float | None = None  # a trial's limit, VR app and headless robot episodes (default: 60 s in VR, robot
    #                                   tasks their own limit)


@dataclass(frozen=True)
class Study:
    name: str
    seed: int
    counterbalance: str
    break_s: float
    quality: dict
    simulated: dict
    conditions: tuple  # (Condition, ...)
    blocks: tuple  # (Block, ...)
    text: str  # the file as read (saved with every session)
    sha256: str
    source: str  # the path, or "default"

    def condition(self, name: str) -> Condition:
        for c in self.conditions:
            if c.name == name:
                return c
        raise StudyError(f"study '{self.name}' has no condition '{name}'")


def _onoff(v, where: str) -> bool:
    if v in ("on", True):
        return True
    if v in ("off", False):
        return False
    raise StudyError(f"{where} must be \"on\" or \"off\", got {v!r}")


def _keys(d: dict, allowed: tuple, where: str) -> None:
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise StudyError(f"{where}: unknown key{'s' if len(extra) > 1 else ''} {', '.join(extra)} "
                         f"(allowed: {', '.join(allowed)})")


def _int(d: dict, key: str, lo: int, hi: int, where: str, default=None) -> int:
    v = d.get(key, default)
    if v is None:
        raise StudyError(f"{where}: '{key}' is required")
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise StudyError(f"{where}: '{key}' must be an integer within {lo}..{hi}, got {v!r}")
    return v


def _listener(d, where: str) -> dict:
    if not isinstance(d, dict):
        raise StudyError(f"{where} must be a table")
    _keys(d, LISTENER_KEYS, where)
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks.orientation import SimulatedListener

    try:
        SimulatedListener(**d)
    except (ConfigError, TypeError) as exc:
        raise StudyError(f"{where}: {exc}") from None
    return dict(d)


def parse_study(text: str, source: str = "<text>") -> Study:
    """A :class:`Study` from TOML text; any mistake is a StudyError naming the key."""
    from sonicverse_core.tasks.registry import TASKS

    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise StudyError(f"{source}: not valid TOML: {exc}") from None
    _keys(d, ("name", "seed", "counterbalance", "break_s", "quality", "simulated_participant", "conditions",
              "blocks"), source)
    name = d.get("name")
    if not isinstance(name, str) or not NAME.match(name):
        raise StudyError(f"{source}: 'name' must be 1-64 letters, digits, - or _ (starting with a letter or digit)")
    seed = _int(d, "seed", 0, 2**31 - 1, source, 0)
    cb = d.get("counterbalance", "latin")
    if cb not in ("latin", "least-filled"):
        raise StudyError(f"{source}: 'counterbalance' must be \"latin\" or \"least-filled\", got {cb!r}")
    brk = d.get("break_s", 0)
    if isinstance(brk, bool) or not isinstance(brk, (int, float)) or not 0 <= brk <= 3600:
        raise StudyError(f"{source}: 'break_s' must be a number of seconds within 0..3600, got {brk!r}")
    quality = d.get("quality", {})
    if not isinstance(quality, dict):
        raise StudyError(f"{source}: [quality] must be a table")
    _keys(quality, ("missed_frames", "xruns", "latency_ms"), f"{source} [quality]")
    for k, v in quality.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise StudyError(f"{source} [quality]: '{k}' must be a number >= 0, got {v!r}")
    quality = {"missed_frames": 5, "xruns": 0, "latency_ms": 40.0, **quality}
    simulated = _listener(d.get("simulated_participant", {}), f"{source} [simulated_participant]")

    conds_d = d.get("conditions")
    if not isinstance(conds_d, dict) or not conds_d:
        raise StudyError(f"{source}: at least one [conditions.NAME] table is required")
    if len(conds_d) > 12:
        raise StudyError(f"{source}: at most 12 conditions (a balanced Latin square of 13+ rows is not practical)")
    conditions = []
    for cname, c in conds_d.items():
        where = f"{source} [conditions.{cname}]"
        if not NAME.match(cname) or not isinstance(c, dict):
            raise StudyError(f"{where}: a condition is a table named with letters, digits, - or _")
        _keys(c, ("hrtf", "reverb", "agent", "home", "simulated"), where)
        home = c.get("home")
        if home is not None:
            from sonicverse_core.scene.spec import load_scene

            try:
                load_scene(home)
            except Exception as exc:  # noqa: BLE001 - any unreadable scene is the user's to fix
                raise StudyError(f"{where}: home {home!r}: {exc}") from None
        conditions.append(Condition(cname, _onoff(c.get("hrtf", "on"), f"{where} hrtf"),
                                    _onoff(c.get("reverb", "on"), f"{where} reverb"), c.get("agent"), home,
                                    _listener(c.get("simulated", {}), f"{where} simulated")))
    names = [c.name for c in conditions]

    blocks_d = d.get("blocks")
    if not isinstance(blocks_d, list) or not blocks_d:
        raise StudyError(f"{source}: at least one [[blocks]] table is required")
    blocks = []
    by_cli = {s.cli: s for s in TASKS.values()}
    for i, b in enumerate(blocks_d):
        where = f"{source} [[blocks]] #{i + 1}"
        if not isinstance(b, dict):
            raise StudyError(f"{where} must be a table")
        _keys(b, ("name", "task", "trials", "practice", "per_condition", "condition", "agent", "mode", "difficulty",
                  "staircase", "time_limit_s"), where)
        limit = b.get("time_limit_s")
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, float))
                                  or not 1 <= limit <= 3600):
            raise StudyError(f"{where}: 'time_limit_s' must be a number of seconds within 1..3600, got {limit!r}")
        task = b.get("task")
        if task not in by_cli:
            raise StudyError(f"{where}: 'task' must be one of {', '.join(by_cli)}, got {task!r}")
        spec = by_cli[task]
        if spec.kind == "embodied" and spec.frame_task is None:
            raise StudyError(f"{where}: {task} has no person in it (a navigation task); use speaker-following, "
                             f"voice-retrieval or orientation-training")
        bname = b.get("name", f"{task}-{i + 1}")
        if not isinstance(bname, str) or not NAME.match(bname):
            raise StudyError(f"{where}: 'name' must be letters, digits, - or _")
        cond = b.get("condition")
        per = b.get("per_condition", cond is None)
        if not isinstance(per, bool):
            raise StudyError(f"{where}: 'per_condition' must be true or false")
        if per and cond is not None:
            raise StudyError(f"{where}: give 'condition' (one fixed condition) or per_condition = true, not both")
        if not per and cond not in names:
            raise StudyError(f"{where}: 'condition' must be one of {', '.join(names)}, got {cond!r}")
        agents = [b.get("agent")] + [c.agent for c in conditions]
        for a in agents:
            if a is not None and (spec.kind != "embodied" or a not in spec.agents):
                raise StudyError(f"{where}: agent {a!r} cannot do {task} (agents: {', '.join(spec.agents)})")
        mode = b.get("mode", "turn")
        if mode not in ("turn", "walk"):
            raise StudyError(f"{where}: 'mode' must be \"turn\" or \"walk\", got {mode!r}")
        difficulty = b.get("difficulty", "duration")
        if difficulty not in ("duration", "reverb", "distractor"):
            raise StudyError(f"{where}: 'difficulty' must be duration, reverb or distractor, got {difficulty!r}")
        stair = b.get("staircase", "1up2down")
        if stair not in ("1up2down", "1up3down", "none"):
            raise StudyError(f"{where}: 'staircase' must be 1up2down, 1up3down or none, got {stair!r}")
        blocks.append(Block(bname, task, _int(b, "trials", 1, 10_000, where), _int(b, "practice", 0, 1000, where, 0),
                            per, cond, b.get("agent"), mode, difficulty, stair,
                            None if limit is None else float(limit)))
    if len({b.name for b in blocks}) != len(blocks):
        raise StudyError(f"{source}: block names must differ")
    return Study(name, seed, cb, float(brk), quality, simulated, tuple(conditions), tuple(blocks), text,
                 hashlib.sha256(text.encode()).hexdigest(), source)


def load_study(ref: str | Path) -> Study:
    """``"default"`` (the study that ships with the project) or a study file's path."""
    if str(ref) == "default":
        return parse_study(resources.files("app.study").joinpath("default.toml").read_text(), "default")
    p = Path(ref)
    if not p.is_file():
        raise StudyError(f"no study file at '{p}' (give a .toml study file or 'default')")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StudyError(f"cannot read the study file '{p}': {exc}") from None
    return parse_study(text, str(p))
