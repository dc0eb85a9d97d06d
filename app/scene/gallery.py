"""`sonicverse scene gallery`: how a home looks: every room from eye height (from the corner farthest from the room's
centre, looking at it) and a close-up of every furniture category, rendered by the robot camera's renderer (the
look the VR views and the robot share), in one PNG contact sheet."""
from __future__ import annotations

import numpy as np


def _label(img: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    d.rectangle((0, 0, 8 + 6 * len(text), 14), fill=(0, 0, 0))
    d.text((4, 2), text, fill=(255, 255, 255))
    return np.asarray(im)


def _close_up(scene, rc, o):
    """(x, y, z, yaw, pitch) of a camera looking at object ``o`` from its front (or round it), close, with nothing
    of the structure or of another object in between; None when no such place exists."""
    lo, hi = o.mesh.bounds
    size = float(np.max(hi - lo))
    centre = o.pose[:3, :3] @ ((lo + hi) / 2) + o.pose[:3, 3]
    fwd = o.pose[:3, 1]
    zc = float(np.clip(centre[2] + 0.6 * size, scene.floor_z + 0.7, scene.floor_z + 2.2))
    for dist in (1.4 * size + 0.4, 1.0 * size + 0.4, 0.7 * size + 0.4):
        for turn in (0, 30, -30, 60, -60, 90, -90, 180):
            a = np.radians(turn)
            d = np.array([fwd[0] * np.cos(a) - fwd[1] * np.sin(a), fwd[0] * np.sin(a) + fwd[1] * np.cos(a), 0.0])
            p = centre + d * dist
            p[2] = zc
            target = centre + (p - centre) * (0.45 * size / max(dist, 1e-9))  # the object's near side
            if not rc.line_of_sight(p, target)[0]:
                continue
            if not rc.line_of_sight(p, centre, include_dynamic=False)[0]:
                continue
            v = centre - p
            return (p[0], p[1], p[2], float(np.degrees(np.arctan2(v[1], v[0]))),
                    float(np.degrees(np.arctan2(v[2], np.hypot(v[0], v[1])))))
    return None


def gallery(specs: list[str], out, size=(320, 240), eye: float = 1.6, look: str = "home") -> dict:
    from PIL import Image

    from sonicverse_core.geometry.raycast import SceneRayCaster
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.sensors.camera import RGBDCamera

    w, h = size
    rooms, close = {}, {}
    cam = None
    try:
        for spec in specs:
            scene = load_scene(spec)
            if cam is None:
                cam = RGBDCamera(scene, w, h, 90.0, depth=False, look=look)
            cam.set_scene(scene)
            for r in scene.rooms:
                if r.type in rooms:
                    continue
                c = r.footprint.mean(0)
                far = r.footprint[np.argmax(np.linalg.norm(r.footprint - c, axis=1))]
                p = far + 0.35 * (c - far) / max(np.linalg.norm(c - far), 1e-9)  # in from the corner
                yaw = float(np.degrees(np.arctan2(*(c - p)[::-1])))
                rooms[r.type] = _label(cam.render(p[0], p[1], scene.floor_z + eye, yaw, -12.0)["rgb"],
                                       f"{r.type} ({spec.split(':')[-1]})")
            rc = SceneRayCaster(scene)
            for o in scene.objects:
                if o.category in close:
                    continue
                view = _close_up(scene, rc, o)
                if view is not None:
                    close[o.category] = _label(cam.render(*view)["rgb"], o.category)
    finally:
        if cam is not None:
            cam.close()
    tiles = list(rooms.values()) + [close[k] for k in sorted(close)]
    cols = 5
    rows = int(np.ceil(len(tiles) / cols))
    sheet = np.full((rows * h, cols * w, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = t
    from pathlib import Path

    from sonicverse_core.storage import atomic_write

    out = Path(out)
    jpeg = out.suffix.lower() in (".jpg", ".jpeg")  # textured views compress ~5x better as JPEG
    with atomic_write(out) as fh:
        Image.fromarray(sheet).save(fh, format="JPEG" if jpeg else "PNG", **({"quality": 88} if jpeg else {}))
    return {"out": str(out), "rooms": sorted(rooms), "categories": sorted(close), "tiles": len(tiles)}
