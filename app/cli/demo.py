"""Parts of the main job beyond the scene summary and map: binaural audio at a listener in the living room."""
from __future__ import annotations

import json

import numpy as np


def run_demo_extras(scene, grid, out, seconds: float = 4.0) -> list[str]:
    import soundfile as sf

    from assets_manifest import soundbank
    from sonicverse_core.acoustics.probes import scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    probes = scene_probes(scene)
    r = AcousticRenderer(scene, RenderConfig(), probes=probes)
    sources = []
    for cat in ("standing_tv", "sink", "toilet"):
        obj = next((o for o in scene.objects if o.category == cat), None)
        if obj is not None:
            r.add_source(soundbank.sound(cat, 0), obj.sound_position(), sample_rate=soundbank.SAMPLE_RATE)
            sources.append({"category": cat, "object": obj.name, "position": np.round(obj.position, 2).tolist()})
    living = next((room for room in scene.rooms if room.type == "living room"), scene.rooms[0])
    pos = grid.sample(np.random.default_rng(0), 1, room=living.name)[0]
    r.add_listener((pos[0], pos[1], scene.floor_z + 1.6), 0.0)
    y = r.render(seconds)[0]
    sf.write(out / "binaural.wav", y.T, r.cfg.sample_rate, subtype="FLOAT")
    (out / "audio.json").write_text(json.dumps({
        "listener": np.round(r.listeners[0].position, 2).tolist(), "yaw": 0.0, "sources": sources,
        "subsystems": r.subsystems, "peak": np.abs(y).max(axis=1).tolist(),
        "probes": [p.to_json() for p in probes]}, indent=1))
    return ["binaural.wav", "audio.json"]
