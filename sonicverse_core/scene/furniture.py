"""Furniture that looks like furniture: each category built procedurally from parts (a sofa's base, back, arms,
cushions and legs; a chair's legs, seat and back; a bed's frame, mattress, headboard and pillows...), with styles,
proportions and colour schemes drawn from a Generator, inside the object's footprint box (which stays its collision
and navigation proxy).

Every part carries a name, an acoustic material and a colour: the acoustic engine hears the parts the eye sees (a
cushion is fabric, a table's legs and top are wood, a TV's screen is glass). A part whose material is ``None`` takes
the object's mapped material (the category -> material table, which a user can override), so the mapping still
decides what a sofa sounds like.

Local frame: x across the object (width w), y front to back (depth d, the front at +y: the side away from a wall it
stands against), z up from its base (height h); every part lies within [-w/2, w/2] x [-d/2, d/2] x [0, h].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

WOODS = ((150, 111, 72), (186, 146, 101), (110, 76, 50), (205, 180, 140), (92, 64, 44))
FABRICS = ((120, 130, 145), (160, 72, 60), (88, 110, 84), (200, 190, 170), (70, 80, 110), (140, 120, 150))
PAINTS = ((235, 235, 228), (60, 66, 74), (180, 200, 210), (210, 190, 160))
METAL, CERAMIC, GLASS, DARK = (170, 172, 176), (240, 240, 236), (120, 150, 170), (30, 32, 36)
WOOD_M, FABRIC_M, METAL_M, CERAMIC_M, GLASS_M = "WoodPanel", "CurtainHeavy", "Metal", "PolishedConcreteOrTile", \
    "GlassThin"


@dataclass(frozen=True)
class ObjectPart:
    """A part of an object: its name, acoustic material (None: the object's mapped material), mesh in the object's
    local frame and RGBA colour."""

    name: str
    material: str | None
    mesh: trimesh.Trimesh
    colour: tuple


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _cyl(x, y, z0, z1, r, sections=12) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=sections)
    m.apply_translation((x, y, (z0 + z1) / 2))
    return m


class _Parts(list):
    def add(self, name, material, mesh, colour):
        self.append(ObjectPart(name, material, mesh, tuple(int(c) for c in colour[:3]) + (255,)))
        return self


def _pick(rng, options):
    return options[int(rng.integers(len(options)))]


def _shade(c, k):
    return tuple(int(np.clip(v * k, 0, 255)) for v in c)


def _legs(p: _Parts, w, d, z1, t, material, colour, inset=0.02, round_=False):
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - inset - t / 2), sy * (d / 2 - inset - t / 2)
            mesh = _cyl(x, y, 0.0, z1, t / 2) if round_ else _box((x - t / 2, y - t / 2, 0), (x + t / 2, y + t / 2, z1))
            p.add("leg", material, mesh, colour)


def straight_chair(w, d, h, rng) -> _Parts:
    p = _Parts()
    wood = _pick(rng, WOODS)
    metal_legs = rng.random() < 0.3
    seat = min(0.46, 0.52 * h)
    _legs(p, w, d, seat - 0.04, 0.04, METAL_M if metal_legs else WOOD_M, METAL if metal_legs else wood,
          round_=metal_legs)
    p.add("seat", WOOD_M, _box((-w / 2, -d / 2, seat - 0.04), (w / 2, d / 2, seat)), wood)
    if rng.random() < 0.4:  # an upholstered pad
        p.add("seat pad", FABRIC_M, _box((-w / 2 + 0.03, -d / 2 + 0.06, seat), (w / 2 - 0.03, d / 2 - 0.02,
                                                                                seat + 0.03)), _pick(rng, FABRICS))
    for sx in (-1, 1):  # the back's posts
        x = sx * (w / 2 - 0.04)
        p.add("back post", WOOD_M, _box((x - 0.02, -d / 2, seat), (x + 0.02, -d / 2 + 0.04, h)), wood)
    if rng.random() < 0.5:  # slats
        for k in range(3):
            x = (k - 1) * (w - 0.12) / 3
            p.add("back slat", WOOD_M, _box((x - 0.025, -d / 2 + 0.01, seat + 0.08), (x + 0.025, -d / 2 + 0.03,
                                                                                       h - 0.08)), wood)
        p.add("back rail", WOOD_M, _box((-w / 2 + 0.02, -d / 2, h - 0.08), (w / 2 - 0.02, -d / 2 + 0.04, h)), wood)
    else:
        p.add("back", WOOD_M, _box((-w / 2 + 0.02, -d / 2, seat + 0.2), (w / 2 - 0.02, -d / 2 + 0.03, h)), wood)
    return p


def stool(w, d, h, rng) -> _Parts:
    p = _Parts()
    wood = _pick(rng, WOODS)
    r = min(w, d) / 2
    if rng.random() < 0.5:
        p.add("seat", None, _cyl(0, 0, h - 0.04, h, r, 16), _pick(rng, FABRICS + WOODS))
        for k in range(3):
            a = 2 * np.pi * k / 3 + np.pi / 2
            p.add("leg", WOOD_M, _cyl(0.7 * r * np.cos(a), 0.7 * r * np.sin(a), 0, h - 0.04, 0.02), wood)
    else:
        p.add("seat", None, _box((-w / 2, -d / 2, h - 0.04), (w / 2, d / 2, h)), wood)
        _legs(p, w, d, h - 0.04, 0.035, WOOD_M, wood)
        p.add("rung", WOOD_M, _box((-w / 2 + 0.04, -0.01, 0.18), (w / 2 - 0.04, 0.01, 0.2)), wood)
    return p


def breakfast_table(w, d, h, rng) -> _Parts:
    p = _Parts()
    wood = _pick(rng, WOODS)
    p.add("top", WOOD_M, _box((-w / 2, -d / 2, h - 0.04), (w / 2, d / 2, h)), wood)
    if rng.random() < 0.75:
        _legs(p, w, d, h - 0.04, 0.05, WOOD_M, _shade(wood, 0.85), inset=0.05)
        p.add("apron", WOOD_M, _box((-w / 2 + 0.07, -d / 2 + 0.07, h - 0.12),
                                    (w / 2 - 0.07, d / 2 - 0.07, h - 0.041)),
              _shade(wood, 0.9))
    else:
        p.add("pedestal", METAL_M, _cyl(0, 0, 0.03, h - 0.04, 0.05), DARK)
        p.add("foot", METAL_M, _cyl(0, 0, 0, 0.03, min(w, d) * 0.3, 16), DARK)
    return p


def _cabinet(p: _Parts, w, d, h, rng, body, fronts: int, drawers: bool, top_material=WOOD_M, top_colour=None):
    p.add("plinth", WOOD_M, _box((-w / 2 + 0.02, -d / 2, 0), (w / 2 - 0.02, d / 2 - 0.05, 0.08)), _shade(body, 0.6))
    p.add("body", WOOD_M, _box((-w / 2, -d / 2, 0.08), (w / 2, d / 2 - 0.02, h - 0.03)), body)
    p.add("top", top_material, _box((-w / 2, -d / 2, h - 0.03), (w / 2, d / 2, h)), top_colour or body)
    fw = (w - 0.02) / fronts
    for k in range(fronts):
        x0 = -w / 2 + 0.01 + k * fw
        if drawers:
            rows = 3
            fh = (h - 0.13) / rows
            for j in range(rows):
                z0 = 0.09 + j * fh
                p.add("drawer front", WOOD_M, _box((x0 + 0.005, d / 2 - 0.02, z0 + 0.005),
                                                   (x0 + fw - 0.005, d / 2 - 0.004, z0 + fh - 0.005)),
                      _shade(body, 1.08))
                p.add("handle", METAL_M, _box((x0 + fw / 2 - 0.05, d / 2 - 0.006, z0 + fh / 2 - 0.008),
                                              (x0 + fw / 2 + 0.05, d / 2, z0 + fh / 2 + 0.008)), METAL)
        else:
            p.add("door front", WOOD_M, _box((x0 + 0.005, d / 2 - 0.02, 0.09), (x0 + fw - 0.005, d / 2 - 0.004,
                                                                               h - 0.04)),
                  _shade(body, 1.08))
            hx = x0 + (fw - 0.05 if k % 2 == 0 else 0.05)
            p.add("handle", METAL_M, _box((hx - 0.008, d / 2 - 0.006, h - 0.25), (hx + 0.008, d / 2, h - 0.1)),
                  METAL)


def bottom_cabinet(w, d, h, rng) -> _Parts:
    p = _Parts()
    body = _pick(rng, WOODS + PAINTS)
    _cabinet(p, w, d, h, rng, body, max(1, int(round(w / 0.45))), rng.random() < 0.5)
    return p


def countertop(w, d, h, rng) -> _Parts:
    p = _Parts()
    body = _pick(rng, PAINTS + WOODS)
    stone = rng.random() < 0.5
    _cabinet(p, w, d, h, rng, body, max(1, int(round(w / 0.5))), rng.random() < 0.3,
             top_material="Marble" if stone else WOOD_M, top_colour=(200, 200, 196) if stone else _pick(rng, WOODS))
    return p


def shelf(w, d, h, rng) -> _Parts:
    p = _Parts()
    wood = _pick(rng, WOODS + PAINTS)
    t = 0.025
    for sx in (-1, 1):
        x = sx * (w / 2 - t / 2)
        p.add("side", WOOD_M, _box((x - t / 2, -d / 2, 0), (x + t / 2, d / 2, h)), wood)
    p.add("back", WOOD_M, _box((-w / 2 + t, -d / 2, 0), (w / 2 - t, -d / 2 + 0.01, h)), _shade(wood, 0.8))
    n = int(rng.integers(3, 6))
    for k in range(n + 1):
        z = k * (h - t) / n
        p.add("board", WOOD_M, _box((-w / 2 + t, -d / 2 + 0.01, z), (w / 2 - t, d / 2, z + t)), wood)
        if 0 < k < n and rng.random() < 0.7:  # books
            x = -w / 2 + t + 0.02
            while x < w / 2 - t - 0.06:
                bw = float(rng.uniform(0.025, 0.05))
                bh = float(rng.uniform(0.6, 0.9)) * min((h - t) / n - t, 0.3)
                p.add("book", "PlywoodPanel", _box((x, -d / 2 + 0.03, z + t), (x + bw, d / 2 - 0.04, z + t + bh)),
                      _pick(rng, FABRICS + PAINTS))
                x += bw + float(rng.uniform(0.0, 0.08))
    return p


def sofa(w, d, h, rng) -> _Parts:
    p = _Parts()
    fabric = _pick(rng, FABRICS)
    arm = float(rng.uniform(0.12, 0.2))
    seat = 0.42
    # base and back 2 mm inside the arms' outer faces (no coplanar faces of different shades)
    p.add("base", None, _box((-w / 2 + 0.002, -d / 2 + 0.01, 0.08), (w / 2 - 0.002, d / 2 - 0.02, seat - 0.12)),
          _shade(fabric, 0.85))
    p.add("back", None, _box((-w / 2 + 0.002, -d / 2 + 0.002, 0.08), (w / 2 - 0.002, -d / 2 + 0.2, h)),
          _shade(fabric, 0.9))
    for sx in (-1, 1):
        x0, x1 = (w / 2 - arm, w / 2) if sx > 0 else (-w / 2, -w / 2 + arm)
        p.add("arm", None, _box((x0, -d / 2, 0.08), (x1, d / 2, seat + 0.2)), _shade(fabric, 0.9))
    n = 3 if w > 1.7 else 2
    cw = (w - 2 * arm) / n
    for k in range(n):
        x0 = -w / 2 + arm + k * cw
        p.add("seat cushion", FABRIC_M, _box((x0 + 0.01, -d / 2 + 0.2, seat - 0.12), (x0 + cw - 0.01, d / 2 - 0.02,
                                                                                      seat)), fabric)
        p.add("back cushion", FABRIC_M, _box((x0 + 0.02, -d / 2 + 0.2, seat), (x0 + cw - 0.02, -d / 2 + 0.34,
                                                                             h - 0.05)), fabric)
    _legs(p, w, d - 0.02, 0.08, 0.05, WOOD_M, _pick(rng, WOODS), inset=0.04)
    return p


def bed(w, d, h, rng) -> _Parts:
    p = _Parts()
    wood = _pick(rng, WOODS + PAINTS)
    sheet = _pick(rng, ((240, 240, 235), (200, 215, 230), (225, 215, 200)) + FABRICS)
    p.add("frame", WOOD_M, _box((-w / 2, -d / 2 + 0.06, 0.1), (w / 2, d / 2, 0.3)), wood)
    _legs(p, w, d - 0.06, 0.1, 0.06, WOOD_M, wood, inset=0.02)
    # the duvet and the pillows lie on the mattress (their tops above its top: no coplanar faces to fight in depth)
    p.add("mattress", FABRIC_M, _box((-w / 2 + 0.03, -d / 2 + 0.08, 0.3), (w / 2 - 0.03, d / 2 - 0.03, h - 0.04)),
          sheet)
    p.add("headboard", WOOD_M, _box((-w / 2, -d / 2, 0.1), (w / 2, -d / 2 + 0.06, h)), _shade(wood, 0.9))
    n = 2 if w > 1.2 else 1
    pw = (w - 0.2) / n
    for k in range(n):
        x0 = -w / 2 + 0.1 + k * pw
        p.add("pillow", FABRIC_M, _box((x0 + 0.03, -d / 2 + 0.12, h - 0.09), (x0 + pw - 0.03, -d / 2 + 0.5, h)),
              (245, 245, 240))
    p.add("duvet", FABRIC_M, _box((-w / 2 + 0.02, -d / 2 + 0.6, h - 0.07), (w / 2 - 0.02, d / 2 - 0.02, h)),
          _pick(rng, FABRICS))
    return p


def cushion(w, d, h, rng) -> _Parts:
    p = _Parts()
    c = _pick(rng, FABRICS)
    p.add("cushion", None, _box((-w / 2 + 0.02, -d / 2 + 0.02, 0), (w / 2 - 0.02, d / 2 - 0.02, h)), c)
    p.add("piping", None, _box((-w / 2, -d / 2, 0.3 * h), (w / 2, d / 2, 0.7 * h)), _shade(c, 0.8))
    return p


def picture(w, d, h, rng) -> _Parts:
    p = _Parts()
    frame = _pick(rng, WOODS + ((40, 40, 40), (210, 180, 90)))
    t = 0.04
    p.add("canvas", None, _box((-w / 2 + t, -d / 2, t), (w / 2 - t, d / 2 - 0.01, h - t)),
          _pick(rng, ((70, 110, 160), (190, 120, 60), (90, 140, 90), (200, 180, 120), (150, 60, 70))))
    for z0, z1, x0, x1 in ((0, t, -w / 2, w / 2), (h - t, h, -w / 2, w / 2), (t, h - t, -w / 2, -w / 2 + t),
                           (t, h - t, w / 2 - t, w / 2)):
        p.add("frame", WOOD_M, _box((x0, -d / 2, z0), (x1, d / 2, z1)), frame)
    return p


def sink(w, d, h, rng) -> _Parts:
    p = _Parts()
    if d > 0.5:  # a kitchen sink: a cabinet with a basin in its top
        body = _pick(rng, PAINTS + WOODS)
        _cabinet(p, w, d, h - 0.02, rng, body, 2, False, METAL_M, METAL)
        p.add("basin", METAL_M, _box((-w / 2 + 0.08, -d / 2 + 0.1, h - 0.03), (w / 2 - 0.08, d / 2 - 0.08, h - 0.005)),
              _shade(METAL, 0.7))
    else:  # a washbasin on a pedestal
        p.add("pedestal", CERAMIC_M, _box((-0.09, -d / 2 + 0.02, 0), (0.09, -d / 2 + 0.2, h - 0.15)), CERAMIC)
        p.add("basin", CERAMIC_M, _box((-w / 2, -d / 2, h - 0.15), (w / 2, d / 2, h - 0.02)), CERAMIC)
        p.add("bowl", CERAMIC_M, _box((-w / 2 + 0.06, -d / 2 + 0.08, h - 0.025), (w / 2 - 0.06, d / 2 - 0.05,
                                                                                   h - 0.015)), _shade(CERAMIC, 0.85))
    p.add("tap", METAL_M, _cyl(0, -d / 2 + 0.05, h - 0.02, h, 0.015), METAL)
    return p


def toilet(w, d, h, rng) -> _Parts:
    p = _Parts()
    tank = 0.18
    p.add("tank", CERAMIC_M, _box((-w / 2, -d / 2, 0.4), (w / 2, -d / 2 + tank, h - 0.004)), CERAMIC)
    p.add("base", CERAMIC_M, _box((-0.12, -d / 2 + 0.08, 0), (0.12, d / 2 - 0.12, 0.3)), CERAMIC)
    p.add("bowl", CERAMIC_M, _box((-w / 2 + 0.02, -d / 2 + tank - 0.02, 0.3), (w / 2 - 0.02, d / 2 - 0.02, 0.4)),
          CERAMIC)
    p.add("seat", "PlywoodPanel", _box((-w / 2 + 0.01, -d / 2 + tank, 0.4), (w / 2 - 0.01, d / 2, 0.42)),
          _pick(rng, (CERAMIC, (30, 30, 30), (200, 180, 150))))
    p.add("flush", METAL_M, _box((-0.03, -d / 2 + 0.06, h - 0.006), (0.03, -d / 2 + 0.1, h)), METAL)
    return p


def standing_tv(w, d, h, rng) -> _Parts:
    p = _Parts()
    stand_h = float(rng.uniform(0.4, 0.5))
    wood = _pick(rng, WOODS + ((40, 40, 42),))
    p.add("stand", WOOD_M, _box((-w / 2, -d / 2, 0), (w / 2, d / 2 - 0.004, stand_h)), wood)
    p.add("shelf line", WOOD_M, _box((-w / 2 + 0.02, d / 2 - 0.006, stand_h / 2 - 0.01), (w / 2 - 0.02, d / 2,
                                                                                         stand_h / 2 + 0.01)),
          _shade(wood, 0.7))
    sw = min(w * 0.9, 1.1)
    p.add("neck", METAL_M, _box((-0.04, -0.05, stand_h), (0.04, 0.0, stand_h + 0.08)), DARK)
    p.add("foot", METAL_M, _box((-0.15, -0.12, stand_h), (0.15, 0.08, stand_h + 0.01)), DARK)
    p.add("bezel", METAL_M, _box((-sw / 2, -0.06, stand_h + 0.08), (sw / 2, -0.02, h)), DARK)
    p.add("screen", GLASS_M, _box((-sw / 2 + 0.015, -0.02, stand_h + 0.095), (sw / 2 - 0.015, -0.015, h - 0.015)),
          (20, 24, 34))
    return p


def shower(w, d, h, rng) -> _Parts:
    p = _Parts()
    p.add("tray", CERAMIC_M, _box((-w / 2, -d / 2, 0), (w / 2, d / 2, 0.06)), CERAMIC)
    p.add("glass front", GLASS_M, _box((-w / 2, d / 2 - 0.01, 0.06), (w / 2, d / 2, h - 0.05)), GLASS)
    p.add("glass side", GLASS_M, _box((w / 2 - 0.01, -d / 2, 0.06), (w / 2, d / 2 - 0.01, h - 0.05)), GLASS)
    p.add("rail", METAL_M, _box((-w / 2, d / 2 - 0.02, h - 0.05), (w / 2, d / 2, h)), METAL)
    p.add("pole", METAL_M, _cyl(0, -d / 2 + 0.04, 0.9, 1.95 if h > 1.95 else h - 0.05, 0.012), METAL)
    p.add("head", METAL_M, _cyl(0, -d / 2 + 0.1, h - 0.12, h - 0.1, 0.07), METAL)
    return p


def bathtub(w, d, h, rng) -> _Parts:
    p = _Parts()
    rim = 0.06
    p.add("bottom", CERAMIC_M, _box((-w / 2, -d / 2, 0), (w / 2, d / 2, 0.12)), CERAMIC)
    for x0, x1, y0, y1 in ((-w / 2, w / 2, -d / 2, -d / 2 + rim), (-w / 2, w / 2, d / 2 - rim, d / 2),
                           (-w / 2, -w / 2 + rim, -d / 2, d / 2), (w / 2 - rim, w / 2, -d / 2, d / 2)):
        p.add("wall", CERAMIC_M, _box((x0, y0, 0.12), (x1, y1, h)), CERAMIC)
    if rng.random() < 0.3:
        p.add("water", "WaterOrIceSurface", _box((-w / 2 + rim, -d / 2 + rim, 0.12), (w / 2 - rim, d / 2 - rim,
                                                                                      0.14)), (190, 215, 230))
    p.add("tap", METAL_M, _box((-w / 2 + 0.12, -d / 2 + 0.03, h - 0.09), (-w / 2 + 0.18, -d / 2 + rim + 0.05,
                                                                          h - 0.03)), METAL)  # a spout
    return p


def door(w, d, h, rng, z0: float = 0.0) -> _Parts:
    """A door leaf (its local frame: the hinge at x = 0, the leaf along +x) with a handle on each face."""
    p = _Parts()
    c = _pick(rng, WOODS + PAINTS)
    p.add("leaf", None, _box((0.0, -d / 2, z0), (w, d / 2, h)), c)
    hx, hz = w - 0.1, z0 + 1.0
    for s in (-1, 1):
        y0, y1 = (d / 2, d / 2 + 0.004) if s > 0 else (-d / 2 - 0.004, -d / 2)
        p.add("handle", METAL_M, _box((hx - 0.06, y0, hz - 0.01), (hx + 0.02, y1, hz + 0.01)), METAL)
    return p


BUILDERS = {"straight_chair": straight_chair, "stool": stool, "breakfast_table": breakfast_table,
            "bottom_cabinet": bottom_cabinet, "countertop": countertop, "shelf": shelf, "sofa": sofa, "bed": bed,
            "cushion": cushion, "picture": picture, "sink": sink, "toilet": toilet, "standing_tv": standing_tv,
            "shower": shower, "bathtub": bathtub}


def build(category: str, w: float, d: float, h: float, rng: np.random.Generator) -> tuple:
    """The parts of an object of ``category`` in a w x d x h box (a box of the object's own material for a
    category without a builder)."""
    f = BUILDERS.get(category)
    if f is None:
        return (ObjectPart(category, None, _box((-w / 2, -d / 2, 0), (w / 2, d / 2, h)), (150, 150, 150, 255)),)
    return tuple(f(w, d, h, rng))


def turtlebot(cfg=None) -> tuple:
    """A TurtleBot 2 in its local frame (base on z = 0, facing +x): the Kobuki base with its bumper, three plates on
    standoffs up to ``height``, the depth camera on the top plate and the two microphones beside it at
    ``ear_height`` (``ear_spacing`` apart), as :class:`ObjectPart` parts."""
    from sonicverse_core.world.robot import RobotConfig

    c = cfg or RobotConfig()
    r, top = c.radius, c.height
    p = _Parts()
    p.add("base", "Metal", _cyl(0, 0, 0.01, 0.09, r, 32), (45, 47, 52))
    for a in np.radians(np.linspace(-70, 70, 9)):  # the bumper: blocks round the front of the base
        seg = _box((-0.008, -0.022, 0.03), (0.0, 0.022, 0.07))
        seg.apply_transform(trimesh.transformations.rotation_matrix(a, (0, 0, 1)))
        seg.apply_translation((r * np.cos(a), r * np.sin(a), 0))
        p.add("bumper", "Metal", seg, (25, 25, 28))
    for z in (0.13, 0.25, top - 0.01):
        p.add("plate", "PlywoodPanel", _cyl(0, 0, z, z + 0.01, r - 0.02, 32), (30, 30, 32))
    for k in range(6):
        a = 2 * np.pi * k / 6 + np.pi / 6
        p.add("standoff", "Metal", _cyl(0.8 * (r - 0.02) * np.cos(a), 0.8 * (r - 0.02) * np.sin(a), 0.09, top - 0.01,
                                        0.006, 8), METAL)
    cam_z = c.camera_height
    p.add("camera mount", "Metal", _box((-0.02, -0.02, top), (0.02, 0.02, cam_z - 0.02)), DARK)
    p.add("camera", "Metal", _box((-0.03, -0.09, cam_z - 0.02), (0.03, 0.09, cam_z + 0.02)), (20, 20, 22))
    p.add("lens", "GlassThin", _box((0.03, -0.012, cam_z - 0.012), (0.036, 0.012, cam_z + 0.012)), (60, 90, 140))
    for s in (-1, 1):
        y = s * c.ear_spacing / 2
        p.add("microphone", "Metal", _cyl(0, y, c.ear_height - 0.015, c.ear_height + 0.015, 0.012, 12), (200, 40, 40))
    return tuple(p)


def person(height: float = 1.75, radius: float = 0.25, shirt=(70, 100, 150), trousers=(50, 55, 70),
           skin=(225, 184, 150)) -> tuple:
    """A standing person in its local frame (feet on z = 0, facing +x) within ``radius`` of its axis: legs and shoes,
    hips, a torso, shoulders, arms and hands at its sides, a neck and a head with a nose, as parts."""
    h = height
    p = _Parts()
    leg_top = 0.47 * h
    for s in (-1, 1):
        y = s * 0.085
        p.add("shoe", "CurtainHeavy", _box((-0.05, y - 0.045, 0), (0.12, y + 0.045, 0.06)), (40, 35, 30))
        p.add("leg", "CurtainHeavy", _cyl(0, y, 0.06, leg_top, 0.075, 12), trousers)
    p.add("hips", "CurtainHeavy", _box((-0.1, -0.16, leg_top - 0.04), (0.1, 0.16, leg_top + 0.08)), trousers)
    shoulder = 0.82 * h
    p.add("torso", "CurtainHeavy", _box((-0.12, -0.18, leg_top + 0.08), (0.12, 0.18, shoulder)), shirt)
    p.add("shoulders", "CurtainHeavy", _box((-0.11, -0.21, shoulder - 0.06), (0.11, 0.21, shoulder + 0.02)), shirt)
    arm_y = min(0.2, radius - 0.05)  # the arms hang against the torso
    for s in (-1, 1):
        y = s * arm_y
        p.add("arm", "CurtainHeavy", _cyl(0.02, y, leg_top + 0.06, shoulder, 0.045, 10), shirt)
        p.add("hand", "CurtainHeavy", _box((-0.03, y - 0.025, leg_top - 0.04), (0.04, y + 0.025, leg_top + 0.06)),
              skin)
    p.add("neck", "CurtainHeavy", _cyl(0, 0, shoulder + 0.02, shoulder + 0.06, 0.05, 10), skin)
    head = trimesh.creation.icosphere(subdivisions=2, radius=0.11)
    head.apply_scale((0.95, 0.85, 1.05))
    head.apply_translation((0, 0, h - 0.12))
    p.add("head", "CurtainHeavy", head, skin)
    p.add("hair", "CurtainHeavy", _box((-0.1, -0.085, h - 0.06), (0.06, 0.085, h)), (60, 45, 35))
    p.add("nose", "CurtainHeavy", _box((0.09, -0.015, h - 0.15), (0.125, 0.015, h - 0.11)), skin)
    return tuple(p)
