"""The home's look (sonicverse_core/scene/look.py): the texture atlas, faces cut into pieces that each lie in one
texture period, the light baked per vertex (inverse-square lamps, shadows, ambient occlusion; finite and in range),
the trim, the cache, and the renderers that draw it (the CPU path's FLAT shader, the lit path with shadows)."""
import numpy as np
import pytest
import trimesh

from sonicverse_core.scene import look
from sonicverse_core.scene.model import Scene, SceneObject, yaw_pose
from sonicverse_core.scene.shoebox import make_shoebox
from sonicverse_core.scene.spec import load_scene


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SONICVERSE_CACHE", str(tmp_path / "cache"))


def test_atlas_tiles_share_a_mean_and_their_gutters_wrap():
    img, rects = look.atlas()
    assert img.dtype == np.uint8 and img.shape[2] == 4 and (img[..., 3] == 255).all()
    assert set(rects) == set(look.KINDS)
    H, W = img.shape[:2]
    for kind, (u0, v0, u1, v1) in rects.items():
        assert 0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1
        x0, x1 = round(u0 * W), round(u1 * W)
        y0, y1 = round((1 - v1) * H), round((1 - v0) * H)
        assert x1 - x0 == y1 - y0 == look.TILE
        tile = img[y0:y1, x0:x1, :3].astype(float) / 255
        if kind != "sky":  # brightness comes from the vertex colours: every pattern has the same mean
            assert tile.mean() == pytest.approx(look.TEXTURE_MEAN, abs=0.01), kind
            g = look.GUTTER  # the gutter repeats the tile's far side: mip levels 0..log2(GUTTER) do not bleed
            assert np.array_equal(img[y0:y1, x0 - g:x0, :3], img[y0:y1, x1 - g:x1, :3])
            assert np.array_equal(img[y0 - g:y0, x0:x1, :3], img[y1 - g:y1, x0:x1, :3])
    assert look.atlas_bytes() == img.nbytes * 4 // 3


def test_tessellation_keeps_area_and_puts_every_piece_in_one_period():
    rng = np.random.default_rng(3)
    tri = rng.uniform(-2.3, 3.1, (40, 3, 3))
    tri[:20, :, 2] = 0.7  # floor-like triangles (plane z), the rest any orientation
    kinds = np.array(["wood"] * 20 + ["fabric"] * 20, object)
    T, S, uv = look.tessellate(tri, kinds)

    def area(t):
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    assert np.allclose(np.bincount(S, area(T), minlength=40), area(tri), rtol=1e-9, atol=1e-12)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    dom = np.argmax(np.abs(n), 1)[S]
    for k, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        sel = dom == k
        for ax in (a, b):
            c = T[sel][:, :, ax] / look.GRID
            cell = np.floor(c.mean(1, keepdims=True))
            assert np.all(c >= cell - 1e-6) and np.all(c <= cell + 1 + 1e-6)  # one grid cell per piece
    _, rects = look.atlas()
    for i, kind in enumerate(kinds[S]):
        u0, v0, u1, v1 = rects[kind]
        assert np.all(uv[i, :, 0] >= u0 - 1e-9) and np.all(uv[i, :, 0] <= u1 + 1e-9)
        assert np.all(uv[i, :, 1] >= v0 - 1e-9) and np.all(uv[i, :, 1] <= v1 + 1e-9)
    # on a floor the texture repeats every PERIOD metres: u is the position within the period
    f = np.nonzero(dom == 2)[0][0]
    u0, _, u1, _ = rects[kinds[S[f]]]
    x = T[f, :, 0] / look.PERIOD["wood"]
    assert np.allclose((uv[f, :, 0] - u0) / (u1 - u0), x - np.floor(x.mean()), atol=1e-9)


def _lamp_room(objects=()):
    sc = make_shoebox(6.0, 5.0, 2.8)
    return Scene(sc.name, sc.static, list(objects), sc.rooms, metadata={"seed": 0})


def _caster(scene):
    return look._caster(scene)


def test_lamp_light_falls_with_the_square_of_distance_and_ambient_occlusion_darkens_corners():
    sc = _lamp_room()
    lamp = look.lamps(sc)[0]
    assert np.allclose(lamp, (3.0, 2.5, 2.8 - look.LAMP_DROP))
    up = np.array([[0, 0, 1.0]] * 2)
    pts = np.array([[3.0, 2.5, 0.0], [3.0, 2.5, 0.25]])  # straight below the lamp, open all round (below E_MAX)
    E = look.bake_light(sc, pts, up, _caster(sc), np.random.default_rng(0))
    lamp_part = E[:, 0] - look.AMBIENT  # red: the lamp's (1.0) and the ambient's (1.0) share
    d = lamp[2] - pts[:, 2] - 2e-3  # rays leave 2 mm off the surface
    assert lamp_part[0] == pytest.approx(look.LAMP_POWER / d[0] ** 2, rel=1e-3)
    assert lamp_part[1] / lamp_part[0] == pytest.approx((d[0] / d[1]) ** 2, rel=1e-3)
    corner = look.bake_light(sc, np.array([[0.02, 0.02, 0.02]]), np.array([[0, 0, 1.0]]), _caster(sc),
                             np.random.default_rng(0))
    open_floor = look.bake_light(sc, np.array([[0.02 + 3, 0.02 + 2, 0.02]]), np.array([[0, 0, 1.0]]), _caster(sc),
                                 np.random.default_rng(0))
    ambient_corner = corner[0, 0] - look.LAMP_POWER * (lamp - [0.02, 0.02, 0.02])[2] / \
        np.linalg.norm(lamp - [0.02, 0.02, 0.02]) ** 3
    assert ambient_corner < 0.75 * look.AMBIENT < open_floor[0, 0]


def test_furniture_casts_a_shadow_and_the_baked_light_is_finite_and_in_range():
    table = SceneObject("table", "breakfast_table", "WoodPanel",
                        trimesh.creation.box(extents=(1.2, 1.2, 0.05)), pose=yaw_pose(3.0, 2.5, 0.75, 0.0))
    sc = _lamp_room([table])
    pts = np.array([[3.0, 2.5, 0.0], [5.2, 2.5, 0.0]])  # under the table; beside it, in the lamp's light
    E = look.bake_light(sc, pts, np.array([[0, 0, 1.0]] * 2), _caster(sc), np.random.default_rng(0))
    lamp_part = E[:, 0] - look.AMBIENT  # the table is 0.75 m up: no occlusion of the ambient light on the floor
    assert abs(lamp_part[0]) < 1e-9 and lamp_part[1] > 0.2
    lk = look.bake(load_scene("builtin:apartment?seed=3"))
    for arrays in [lk.static, *lk.objects.values()]:
        for k in ("col", "alb"):
            assert np.isfinite(arrays[k]).all() and arrays[k].min() >= 0 and arrays[k].max() <= 1
        assert len(arrays["pos"]) == len(arrays["uv"]) == len(arrays["col"]) == 3 * len(arrays["face"])
    assert 0 < lk.bake_s < 10


def test_a_vertex_hidden_inside_a_solid_takes_its_triangles_visible_light():
    E = np.array([[0.2, 0.2, 0.2], [np.nan] * 3, [0.4, 0.4, 0.4], [np.nan] * 3, [np.nan] * 3, [np.nan] * 3])
    out = look.fill_hidden(E)
    assert np.allclose(out[1], 0.3) and np.allclose(out[3:], 0.0)
    # in a home: a point inside a wall is found hidden (NaN, to be filled); one in a room is lit
    sc = load_scene("builtin:apartment")
    wall = next(b for n, b in zip(sc.static_mesh().part_names, look._part_boxes(sc, "wall")) if n.startswith("wall"))
    pts = np.array([(wall[0] + wall[1]) / 2, [*sc.rooms[0].footprint.mean(0), 0.0]])
    E = look.bake_light(sc, pts, np.array([[1.0, 0, 0], [0, 0, 1.0]]), _caster(sc), np.random.default_rng(0))
    assert np.isnan(E[0]).all() and np.isfinite(E[1]).all() and E[1, 0] > look.AMBIENT * 0.5
    lk = look.bake(sc)  # and nothing hidden is left in what is drawn
    assert np.isfinite(lk.static["col"]).all()


def test_trim_follows_the_walls_but_not_across_doors():
    sc = load_scene("builtin:apartment?seed=1")
    trim = look.trim(sc, _caster(sc))
    names = [n for n, _ in trim]
    doors = look._part_boxes(sc, "threshold")
    windows = look._part_boxes(sc, "window")
    assert sum(n.startswith("door frame") for n in names) == 6 * len(doors)  # jambs and a head on both faces
    assert sum(n.startswith("window frame") for n in names) == 8 * len(windows)
    assert sum(n.startswith("skirting") for n in names) >= len(sc.rooms) * 4
    for n, m in trim:
        if not n.startswith("skirting"):
            continue
        lo, hi = m.bounds
        assert hi[2] <= look.SKIRTING_H + 1e-9
        for b in doors:  # a skirting board never crosses a door opening
            overlap = np.minimum(hi[:2], b[1, :2]) - np.maximum(lo[:2], b[0, :2])
            assert not np.all(overlap > 1e-6), (n, b)
        assert sc.room_at((lo[:2] + hi[:2]) / 2) is not None  # inside a room, against its walls


def test_the_look_is_cached_in_memory_and_on_disk_and_a_damaged_entry_is_baked_again(tmp_path):
    from assets_manifest import cache_dir

    sc = load_scene("builtin:apartment")
    a = look.home_look(sc)
    assert not a.cached and a.bake_s > 0
    assert look.home_look(sc) is a
    path = cache_dir() / "looks" / f"{look.look_key(sc)}.npz"
    assert path.exists()
    fresh = load_scene("builtin:apartment")
    b = look.home_look(fresh)
    assert b.cached and np.array_equal(a.static["col"], b.static["col"]) and set(a.objects) == set(b.objects)
    path.write_bytes(b"not an npz")
    c = look.home_look(load_scene("builtin:apartment"))
    assert not c.cached and np.array_equal(a.static["col"], c.static["col"])
    moved = load_scene("builtin:apartment")  # a scene whose furniture stands elsewhere is another look
    o = next(o for o in moved.objects if o.category == "stool")
    moved.move_object(o.name, yaw_pose(*(o.position + [0.1, 0, 0]), 0.0))
    assert look.look_key(moved) != look.look_key(sc)


def test_camera_draws_the_baked_look_and_the_lit_path_with_shadows():
    from sonicverse_core.sensors.camera import RenderScene, RGBDCamera

    sc = load_scene("builtin:apartment")
    lk = look.home_look(sc)
    rs = RenderScene(sc, look="home")
    assert sum(rs.group_triangles.values()) == lk.triangles
    prims = [p for node in rs.group_nodes.values() for p in node.mesh.primitives]
    # the CPU path: textured parts in one primitive, plaster and plain ones (near-uniform tiles) without the texture
    assert sorted(p.material.baseColorTexture is None for p in prims) == [False, True]
    assert sum(len(p.positions) for p in prims) == 3 * lk.triangles
    room = next(r for r in sc.rooms if r.type == "living room")
    c = room.footprint.mean(0)
    imgs = {}
    for name in ("home", "flat", "pbr"):
        cam = RGBDCamera(sc, 96, 72, 90.0, look=name)
        try:
            out = cam.render(c[0], c[1], 1.5, 30.0, -20.0)
        finally:
            cam.close()
        imgs[name] = out["rgb"].astype(float)
        assert np.isfinite(out["depth"]).all() and (out["depth"] > 0).mean() > 0.99
    # textures: the home look has more detail than one colour per face; the lit path differs from the baked one
    def detail(im):
        return np.abs(np.diff(im, axis=1)).mean()

    assert detail(imgs["home"]) > detail(imgs["flat"])
    assert np.abs(imgs["pbr"] - imgs["home"]).mean() > 2.0
    with pytest.raises(Exception, match="look"):
        RGBDCamera(sc, 32, 32, look="shiny")


def test_lit_path_lamps_follow_the_viewer():
    from sonicverse_core.sensors.camera import RenderScene

    sc = load_scene("builtin:apartment?seed=1")
    rs = RenderScene(sc, look="pbr")
    assert 0 < len(rs.lamp_nodes) <= 4 < len(rs._lamps)
    far = rs._lamps[-1]
    rs.place_lights(far[:2])
    placed = [rs.scene.get_pose(n)[:3, 3] for n in rs.lamp_nodes]
    assert any(np.allclose(p, far) for p in placed)


def test_a_closed_lit_camera_collected_in_another_ones_frame_leaves_it_drawing():
    """The garbage collector takes a closed camera's renderer whenever it runs, often inside another camera's
    frame. pyrender's second clean-up of that renderer (its ``__del__``) deleted framebuffer 1 of the context then
    current, a lit camera's shadow framebuffer: its next frame failed (glBindFramebuffer: invalid operation). Here
    the collection is made to happen inside the second camera's frame."""
    import gc

    from sonicverse_core.sensors.camera import RGBDCamera

    sc = load_scene("builtin:apartment")
    c = next(r for r in sc.rooms if r.type == "living room").footprint.mean(0)
    first = RGBDCamera(sc, 32, 32, look="pbr")
    first.render(c[0], c[1], 1.5, 0.0)
    held = [first.renderer._renderer]  # the only reference left once it is closed
    first.close()
    second = RGBDCamera(sc, 32, 32, look="pbr")
    try:
        before = second.render(c[0], c[1], 1.5, 0.0)
        inner = second.renderer._renderer
        assert inner._shadow_fb is not None  # drawn with shadows: the framebuffer the old clean-up hit
        update = inner._update_context

        def update_then_collect(*a, **kw):  # the collector runs in this frame, with this context current
            update(*a, **kw)
            held.clear()
            gc.collect()

        inner._update_context = update_then_collect
        second.render(c[0], c[1], 1.5, 0.0)
        del inner._update_context
        assert not held
        after = second.render(c[0], c[1], 1.5, 0.0)
    finally:
        second.close()
    assert np.array_equal(after["rgb"], before["rgb"]) and np.array_equal(after["depth"], before["depth"])


def test_a_closed_camera_leaves_no_egl_context_current():
    """Closing releases the camera's EGL context before destroying it: a context destroyed while current is only
    marked, and freed inside the next camera's ``eglMakeCurrent`` (the likely cause of a corrupted heap, once in a
    few hundred runs of ``sonicverse bench camera``). PyOpenGL wraps each handle anew, so the old check (``==``)
    never saw its own context current."""
    from sonicverse_core.sensors.camera import RGBDCamera
    from sonicverse_core.sensors.offscreen import current_egl_context

    sc = load_scene("builtin:apartment")
    c = next(r for r in sc.rooms if r.type == "living room").footprint.mean(0)
    cam = RGBDCamera(sc, 32, 32, semantic=True)
    cam.render(c[0], c[1], 1.5, 0.0)
    assert current_egl_context() != 0  # pyrender leaves the last context that drew current
    cam.close()
    assert current_egl_context() == 0


def test_an_unclosed_camera_collected_in_another_ones_frame_leaves_that_frame_in_its_own_context():
    """The collector takes a renderer nobody closed (an env dropped in a notebook) inside another camera's frame:
    its clean-up makes its own context current to free its GL objects, and pyrender's left it so, destroyed, for
    the rest of that frame. Here the context that was current is given back."""
    import gc

    from sonicverse_core.sensors.camera import RGBDCamera
    from sonicverse_core.sensors.offscreen import current_egl_context

    sc = load_scene("builtin:apartment")
    c = next(r for r in sc.rooms if r.type == "living room").footprint.mean(0)
    first = RGBDCamera(sc, 32, 32, look="pbr")
    first.render(c[0], c[1], 1.5, 0.0)
    held = [first.renderer]
    first.renderer = None  # dropped without close(): only ``held`` keeps it
    del first
    second = RGBDCamera(sc, 32, 32, look="pbr")
    try:
        before = second.render(c[0], c[1], 1.5, 0.0)
        inner = second.renderer._renderer
        update = inner._update_context
        seen = []

        def update_then_collect(*a, **kw):  # the collector runs in this frame, with this context current
            update(*a, **kw)
            own = current_egl_context()
            held.clear()
            gc.collect()
            seen.append((own, current_egl_context()))

        inner._update_context = update_then_collect
        during = second.render(c[0], c[1], 1.5, 0.0)
        del inner._update_context
        assert not held and len(seen) == 1 and seen[0][0] != 0 and seen[0][1] == seen[0][0]
        after = second.render(c[0], c[1], 1.5, 0.0)
    finally:
        second.close()
    for frame in (during, after):
        assert np.array_equal(frame["rgb"], before["rgb"]) and np.array_equal(frame["depth"], before["depth"])


def test_no_two_parts_of_different_colours_fight_in_depth():
    """Faces of two parts of an object that lie in the same plane, face the same way and overlap would flicker (the
    depth test cannot order them); parts of one colour may (they draw the same), and downward faces are unseen."""
    def faces(m):
        t = np.asarray(m.vertices)[np.asarray(m.faces)]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return t, n, np.einsum("ij,ij->i", n, t[:, 0])

    def inside(p, tri):
        v0, v1, v2 = tri[2] - tri[0], tri[1] - tri[0], p - tri[0]
        d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
        den = d00 * d11 - d01 * d01
        u, v = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        return u > 1e-6 and v > 1e-6 and u + v < 1 - 1e-6

    for seed in range(8):
        for o in load_scene(f"builtin:apartment?seed={seed}").objects:
            parts = [(name, col, *faces(m)) for name, _, m, col in o.looks()]
            for i in range(len(parts)):
                for j in range(i + 1, len(parts)):
                    a, b = parts[i], parts[j]
                    if a[1] == b[1]:
                        continue
                    for fa in range(len(a[2])):
                        if a[3][fa][2] < -0.9:
                            continue
                        same = (np.abs(b[3] @ a[3][fa] - 1) < 1e-6) & (np.abs(b[4] - a[4][fa]) < 1e-6)
                        for fb in np.nonzero(same)[0]:
                            assert not (inside(a[2][fa].mean(0), b[2][fb]) or inside(b[2][fb].mean(0), a[2][fa])), \
                                (o.name, a[0], b[0])
