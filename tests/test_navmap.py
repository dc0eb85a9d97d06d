"""The navigators' egocentric maps (agents/navmap.py, `sonicverse train --map` on AudioGoal and SemanticAudioNav):
drawn back onto the home, what each channel shows is where the docstrings say it is. (The route map, which runs
sem-nav, is tested with sem-nav in tests/test_semnav.py.)"""
import numpy as np


def _pixels(S: int, res: float):
    """Metres ahead of and to the left of the robot of each pixel of an S x S egocentric map of ``res`` m pixels, as
    the maps' docstrings say (the robot at the centre facing the top, its left to the left): derived here, not taken
    from the code under test."""
    u = (np.arange(S) + 0.5 - S / 2) * res
    return -np.repeat(u[:, None], S, 1), -np.repeat(u[None, :], S, 0)


def _on_home(pose, fwd, left) -> np.ndarray:
    """(n, 2): the home's x, y of points ``fwd`` m ahead of and ``left`` m to the left of a robot at ``pose``."""
    a = np.radians(pose[2])
    return np.stack([pose[0] + np.cos(a) * fwd - np.sin(a) * left, pose[1] + np.sin(a) * fwd + np.cos(a) * left], -1)


def test_the_navigators_map_draws_what_depth_saw_and_is_louder_nearer_the_sound():
    """NavEgoMap (`train --map` on AudioGoal): drawn back onto the home as the docstring says (the robot at the
    centre facing the top, its left to the left, pixels of RES m), the obstacles depth saw lie off the navigable
    floor and the floor it saw lies on floor; the robot's own pixel is on its track; and how loud the sound was at
    the places the oracle drove through falls with their geodesic distance to the goal (Spearman)."""
    from scipy.stats import spearmanr

    from agents.navmap import NavEgoMap
    from agents.scripted import OracleAgent
    from sonicverse_core.tasks import make_env

    env = make_env("AudioGoal", split="val", sensors=("depth", "spectrogram", "pose"), width=64, height=64)
    S, c = NavEgoMap.SIZE, NavEgoMap.SIZE // 2
    fwd, left = _pixels(S, NavEgoMap.RES)
    rhos = []
    try:
        for seed in (1, 2, 3):
            obs, info = env.reset(seed=seed)
            priv = env.unwrapped.privileged()
            w, goal = priv["world"], priv["goals"][0][:2]
            g = w.grid
            oracle, m = OracleAgent(np.random.default_rng(0)), NavEgoMap()
            oracle.reset(env, obs, info)
            m.reset(env, obs, info)
            start = w.pose.copy()
            counts = np.zeros((2, 2))  # [obstacle px off navigable, all], [floor px on floor, all]
            for _ in range(300):
                img = m.observe(obs, info)
                assert img.shape == (NavEgoMap.CHANNELS, S, S) and img.dtype == np.uint8
                assert img[3, c - 2:c + 2, c - 2:c + 2].max() >= 250  # the robot stands on its track
                home = _on_home(w.pose, fwd, left)
                for k, ch in enumerate((0, 1)):
                    sel = img[ch] > 0
                    pts = home[sel]
                    if ch == 0:
                        good = ~g.is_navigable(pts, main_only=False)
                    else:
                        rc = g.cell_of(pts)
                        inside = (rc >= 0).all(1) & (rc < np.array(g.shape)).all(1)
                        rc = np.clip(rc, 0, np.array(g.shape) - 1)
                        good = g.floor[rc[:, 0], rc[:, 1]] & inside
                    counts[k] += (good.sum(), sel.sum())
                obs, _, term, trunc, info = env.step(oracle.act(obs, info))
                if term or trunc:
                    break
            assert info["metrics"]["success"] == 1.0
            assert counts[0, 0] >= 0.9 * counts[0, 1] and counts[1, 0] >= 0.75 * counts[1, 1], counts
            heard = m.level_n > 0
            o = (np.argwhere(heard) - m.n // 2 + 0.5) * m.RES  # odometry frame -> the home's
            a0 = np.radians(start[2])
            xy = np.stack([start[0] + np.cos(a0) * o[:, 0] - np.sin(a0) * o[:, 1],
                           start[1] + np.sin(a0) * o[:, 0] + np.cos(a0) * o[:, 1]], 1)
            geo = g.geodesic_from_field(g.distance_field(goal), xy)
            ok = np.isfinite(geo)
            assert ok.sum() >= 10
            rhos.append(spearmanr((m.level_sum[heard] / m.level_n[heard])[ok], geo[ok])[0])
    finally:
        env.close()
    assert np.median(rhos) <= -0.5 and max(rhos) < 0, rhos


def test_map_semantic_puts_each_category_where_depth_says_it_is():
    """agents.navmap.map_semantic: a sofa straight ahead at 2 m, seen facing +y (yaw 90), lands 2 m along +y of
    the robot with the sofa's bit and no other; pixels of no category (walls) and without depth mark nothing."""
    from agents.navmap import map_semantic
    from sonicverse_core.sensors.camera import CLASSES

    H = W = 8
    depth = np.full((H, W), 2.0)
    depth[:, :2] = 0.0  # no return
    sem = np.full((H, W), CLASSES.index("wall"))
    sem[:, 3:5] = CLASSES.index("sofa")
    lut = np.zeros(len(CLASSES), np.int64)
    lut[CLASSES.index("sofa")] = 1 << CLASSES.index("sofa")
    seen = np.zeros((40, 40), np.int64)
    map_semantic(seen, depth, sem, lut, (1.0, 0.0), 90.0, fx=4.0, cell=0.25, stride=1)
    cells = np.argwhere(seen)
    assert len(cells) and np.all(seen[seen != 0] == lut[CLASSES.index("sofa")])
    xy = (cells - 20 + 0.5) * 0.25
    assert np.allclose(xy.mean(0), (1.0, 2.0), atol=0.2) and np.ptp(xy[:, 1]) <= 0.25, xy


def test_the_semantic_map_names_the_heard_category_and_marks_where_the_camera_saw_it():
    """SemNavMap (`train --map` on SemanticAudioNav): the ears name the goal's category (the shipped SAVi's goal
    predictor, its scores summed over the heard steps: right by the end of these episodes); channel 4 shows only
    cells within 0.6 m of an object of the category named at the time (drawn back onto the home as in the test above), and when the oracle has reached the goal it
    shows the goal's object within 1.5 m of the robot."""
    from agents.maps import MAP_KIND_SENSORS
    from agents.navmap import SemNavMap
    from agents.scripted import OracleAgent
    from assets_manifest.soundbank import CATEGORIES
    from sonicverse_core.tasks import make_env

    env = make_env("SemanticAudioNav", split="val", sensors=MAP_KIND_SENSORS["sem"], width=64, height=64)
    S = SemNavMap.SIZE
    fwd, left = _pixels(S, SemNavMap.RES)
    try:
        for seed in (2, 3):  # (seed 1's goal, a shelf 1.5 m away, is out of the camera's view at the end)
            obs, info = env.reset(seed=seed)
            w = env.unwrapped.privileged()["world"]
            cat = env.unwrapped.episode.category
            boxes = {c: np.array([o.world_bounds()[:, :2] for o in w.scene.objects if o.category == c])
                     for c in CATEGORIES}
            oracle, m = OracleAgent(np.random.default_rng(0)), SemNavMap()
            oracle.reset(env, obs, info)
            m.reset(env, obs, info)
            lit = 0
            for _ in range(500):
                img = m.observe(obs, info)
                assert img.shape == (SemNavMap.CHANNELS, S, S)
                sel = img[4] > 0
                if sel.any():  # every lit pixel at an object of the category named now
                    b = boxes[CATEGORIES[m.category()]]
                    pts = _on_home(w.pose, fwd[sel], left[sel])
                    gap = np.maximum(np.maximum(b[None, :, 0] - pts[:, None], pts[:, None] - b[None, :, 1]), 0)
                    assert np.all(np.linalg.norm(gap, axis=2).min(1) <= 0.6)
                lit += sel.sum()
                obs, _, term, trunc, info = env.step(oracle.act(obs, info))
                if term or trunc:
                    break
            assert info["metrics"]["success"] == 1.0 and m.ears.heard > 0 and lit > 0
            img = m.observe(obs, info)
            assert CATEGORIES[m.category()] == cat  # named right once the sound has been heard out
            c = S // 2
            assert img[4, c - 6:c + 6, c - 6:c + 6].any()  # the goal's object, within 1.5 m
    finally:
        env.close()
