"""Scene specs: one string names a scene.

- ``builtin:apartment?seed=N`` the procedural home (default seed 0)
- ``builtin:l-room``, ``builtin:two-rooms?door=open|closed|sealed``, ``builtin:three-rooms?door=...`` reference
  rooms for sound between rooms
- ``shoebox:LxWxH?material=NAME`` (or ``floor=``, ``ceiling=``, ``walls=``, ``x0=``...)
- a path to a .glb/.gltf/.obj/.ply file
- ``mp3d:DIR`` a Matterport3D house folder, ``igibson:DIR`` an iGibson scene folder

Any spec takes ``mapping=igibson|mp3d|builtin`` or ``mapping=FILE.json`` (a user category -> material table).
"""
from __future__ import annotations

from pathlib import Path
from urllib.parse import parse_qsl

from sonicverse_core.errors import SceneSpecError
from sonicverse_core.scene.mapping import MAPPINGS, CategoryMapping, load_mapping
from sonicverse_core.scene.model import Scene

DEFAULT_SCENE = "builtin:apartment"
KINDS = ("builtin:apartment", "builtin:l-room", "builtin:two-rooms?door=open|closed|sealed",
         "builtin:three-rooms?door=open|closed|sealed", "shoebox:LxWxH", "FILE.glb|.gltf|.obj|.ply", "mp3d:DIR",
         "igibson:DIR")


def _split(spec: str) -> tuple[str, dict[str, str]]:
    head, _, query = spec.partition("?")
    try:
        params = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise SceneSpecError(f"malformed options in scene spec '{spec}' (use key=value&key=value)") from None
    return head, params


def _mapping(params: dict, default: str) -> CategoryMapping:
    name = params.pop("mapping", default)
    if name in MAPPINGS:
        return MAPPINGS[name]
    return load_mapping(name, base=default)


def _unused(spec: str, params: dict) -> None:
    if params:
        raise SceneSpecError(f"scene spec '{spec}': unknown option(s) {', '.join(sorted(params))}")


def load_scene(spec: str = DEFAULT_SCENE) -> Scene:
    """Build or load the scene a spec string names. Raises SceneSpecError / SceneFileError / MeshError."""
    if not isinstance(spec, str) or not spec.strip():
        raise SceneSpecError("empty scene spec; try 'builtin:apartment?seed=0' or 'shoebox:6x4x3'")
    spec = spec.strip()
    head, params = _split(spec)
    if head == "builtin:apartment":
        from sonicverse_core.scene.apartment import generate_apartment

        mapping = _mapping(params, "builtin")
        try:
            seed = int(params.pop("seed", "0"))
        except ValueError:
            raise SceneSpecError(f"scene spec '{spec}': seed must be an integer") from None
        _unused(spec, params)
        return generate_apartment(seed, mapping, spec=spec)
    if head == "builtin:three-rooms":
        from sonicverse_core.scene import reference

        params.pop("mapping", None)
        door = params.pop("door", "open")
        surfaces = {k: params.pop(k) for k in ("west", "middle", "east") if k in params}
        _unused(spec, params)
        return reference.three_rooms(door, **surfaces)
    if head in ("builtin:l-room", "builtin:two-rooms"):
        from sonicverse_core.scene import reference

        params.pop("mapping", None)
        door = params.pop("door", "open") if head == "builtin:two-rooms" else None
        surfaces = {k: params.pop(k) for k in ("west", "east") if k in params} if door is not None else {}
        _unused(spec, params)
        return reference.l_room() if door is None else reference.two_rooms(door, **surfaces)
    if head.startswith("shoebox:"):
        from sonicverse_core.scene.shoebox import make_shoebox

        try:
            L, W, H = (float(v) for v in head[len("shoebox:"):].lower().split("x"))
        except ValueError:
            raise SceneSpecError(f"scene spec '{spec}': write shoebox:LxWxH in metres, e.g. shoebox:6x4x3") from None
        mats = {}
        if "material" in params:
            whole = params.pop("material")
            mats = {s: whole for s in ("floor", "ceiling", "x0", "x1", "y0", "y1")}
        if "walls" in params:
            w = params.pop("walls")
            mats.update({s: w for s in ("x0", "x1", "y0", "y1")})
        for s in ("floor", "ceiling", "x0", "x1", "y0", "y1"):
            if s in params:
                mats[s] = params.pop(s)
        params.pop("mapping", None)
        _unused(spec, params)
        return make_shoebox(L, W, H, mats, spec=spec)
    if head.startswith("mp3d:"):
        from sonicverse_core.scene.loaders.mp3d import load_mp3d

        mapping = _mapping(params, "mp3d")
        _unused(spec, params)
        return load_mp3d(head[5:], mapping, spec=spec)
    if head.startswith("igibson:"):
        from sonicverse_core.scene.loaders.igibson import load_igibson

        mapping = _mapping(params, "igibson")
        _unused(spec, params)
        return load_igibson(head[8:], mapping, spec=spec)
    from sonicverse_core.scene.loaders.mesh import MESH_SUFFIXES, load_mesh_scene

    if Path(head).suffix.lower() in MESH_SUFFIXES or Path(head).exists():
        mapping = _mapping(params, "builtin")
        _unused(spec, params)
        return load_mesh_scene(head, mapping, spec=spec)
    raise SceneSpecError(f"unknown scene spec '{spec}'; use one of: {', '.join(KINDS)}")
