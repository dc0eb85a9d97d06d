"""The `sonicverse` command. Every user mistake prints one line on stderr and exits with code 2."""
from __future__ import annotations

import faulthandler
import json
import logging
import os
import signal
import sys
from pathlib import Path

from app.cli import args as A
from sonicverse_core.errors import SonicverseError, stop, stop_behind, stops_quiet_in_finalisers


def _json(obj) -> None:
    print(json.dumps(obj, indent=None, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def _out_dir(path: str) -> Path:
    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    return p


# --- scene --------------------------------------------------------------------------------------------------
def cmd_scene_info(a) -> int:
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.scene.summary import scene_info

    scene = load_scene(a.spec)
    info = scene_info(scene, NavGrid(scene).navigable_area)
    if a.json:
        _json(info)
    else:
        print(f"{info['name']} ({info['spec']}): {len(info['rooms'])} rooms, {info['floor_area_m2']} m² floor, "
              f"{info['navigable_area_m2']} m² navigable, {info['triangles']} triangles")
        for r in info["rooms"]:
            print(f"  room {r['name']:<14} {r['type']:<12} {r['area_m2']:7.2f} m²")
        for c, n in info["objects_per_category"].items():
            print(f"  {n:3d} x {c}")
        for m, area in info["materials_m2"].items():
            print(f"  {area:9.2f} m² {m}")
        lk = info["look"]
        print(f"  look: {lk['triangles']} triangles, {lk['total_mib']} MiB (vertices {lk['vertex_mib']}, texture "
              f"{lk['texture']} {lk['texture_mib']}), baked in {lk['bake_s']} s"
              + (" (from the cache)" if lk["from_cache"] else ""))
    return 0


def cmd_scene_map(a) -> int:
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.scene.topdown import draw_map

    scene = load_scene(a.spec)
    out = draw_map(scene, a.out, grid=NavGrid(scene))
    print(out)
    return 0


def cmd_scene_gallery(a) -> int:
    from app.scene.gallery import gallery

    res = gallery(a.specs, a.out, look=a.look)
    print(json.dumps(res) if a.json else res["out"])
    return 0


# --- demo ---------------------------------------------------------------------------------------------------
def cmd_demo(a) -> int:
    """The main job on the embedded default scene."""
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.scene.summary import scene_info
    from sonicverse_core.scene.topdown import draw_map

    out = _out_dir(a.out)
    scene = load_scene(a.scene)
    grid = NavGrid(scene)
    info = scene_info(scene, grid.navigable_area)
    (out / "scene.json").write_text(json.dumps(info, indent=2))
    draw_map(scene, out / "map.png", grid=grid)
    written = ["scene.json", "map.png"]
    from app.cli.demo import run_demo_extras

    written += run_demo_extras(scene, grid, out, seconds=a.seconds)
    summary = {"scene": scene.spec, "out": str(out), "files": written,
               "rooms": len(scene.rooms), "floor_area_m2": info["floor_area_m2"]}
    _json(summary) if a.json else print(f"wrote {', '.join(written)} to {out}/")
    return 0


# --- bench --------------------------------------------------------------------------------------------------
def cmd_bench_rays(a) -> int:
    from app.bench.engine import bench_rays

    _json(bench_rays(a.scene, a.rays))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = A.Parser(prog="sonicverse", description="Sonicverse: multisensory household simulation with real-time "
                 "binaural audio.")
    p.add_argument("--version", action="version", version=f"sonicverse {version()}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="log what the library does (-vv: debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sc = sub.add_parser("scene", help="inspect scenes", description="Inspect a scene: summary or top-down map.")
    scs = sc.add_subparsers(dest="scene_command", metavar="SUBCOMMAND", required=True)
    s = scs.add_parser("info", help="rooms, objects, materials, areas", description="Print a scene summary: rooms, "
                       "objects per category, materials with surface areas, floor area, bounds, triangles.")
    s.add_argument("spec", help="scene spec, e.g. builtin:apartment?seed=3, shoebox:6x4x3, FILE.glb, mp3d:DIR")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.set_defaults(func=cmd_scene_info)
    s = scs.add_parser("map", help="draw a top-down map (PNG)", description="Draw a top-down map: navigable "
                       "floor, walls, doors, windows, labelled objects, rooms coloured.")
    s.add_argument("spec", help="scene spec")
    s.add_argument("--out", required=True, type=A.out_file(".png"), help="output PNG file")
    s.set_defaults(func=cmd_scene_map)
    s = scs.add_parser("gallery", help="how homes look: every room type and a close-up of every category (PNG/JPEG)",
                       description="Render every room type from eye height and a close-up of every furniture "
                       "category of the given homes into one contact sheet.")
    s.add_argument("specs", nargs="+", metavar="SPEC", help="scene specs (the first home with a room type is used)")
    s.add_argument("--out", required=True, type=A.out_file(".png", ".jpg", ".jpeg"),
                   help="output file (.png, or .jpg: about 5x smaller for textured views)")
    s.add_argument("--look", default="home", choices=("home", "pbr", "flat"),
                   help="home: textures and baked light (default); pbr: lit per pixel with shadows (the GPU path); "
                   "flat: a colour per face")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.set_defaults(func=cmd_scene_gallery)

    d = sub.add_parser("demo", help="the main job on the default scene", description="Build the default "
                       "apartment and write its map, summary, and a short headless run's outputs to a folder.")
    d.add_argument("--scene", default="builtin:apartment?seed=0", help="scene spec (default: %(default)s)")
    d.add_argument("--out", default="out/demo", type=A.out_dir, help="output folder (default: %(default)s)")
    d.add_argument("--seconds", type=A.number(0, 600, lo_open=True, unit="s"), default=4.0,
                   help="length of the rendered audio, s (default: %(default)s)")
    d.add_argument("--json", action="store_true", help="print one JSON object")
    d.set_defaults(func=cmd_demo)

    b = sub.add_parser("bench", help="benchmarks (print JSON)", description="Benchmarks; each prints one JSON "
                       "object with a reference measured in the same run.")
    bs = b.add_subparsers(dest="bench_command", metavar="BENCH", required=True)
    r = bs.add_parser("rays", help="ray casting rays/s: Embree vs trimesh's numpy caster")
    r.add_argument("--scene", default="builtin:apartment", help="scene spec (default: %(default)s)")
    r.add_argument("--rays", type=A.count(1000, 50_000_000), default=200_000,
                   help="rays per batch (default: %(default)s)")
    r.add_argument("--json", action="store_true", help="(always JSON)")
    r.set_defaults(func=cmd_bench_rays)

    from app.cli.acoustics import add_audio_commands

    add_audio_commands(sub, bs)
    from app.cli.tasks import add_task_commands

    add_task_commands(sub, bs)
    from app.cli.vr import add_vr_commands

    add_vr_commands(sub, bs)
    from app.cli.study import add_study_commands

    add_study_commands(sub)
    return p


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as v

    try:
        return v("sonicverse")
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


def _on_sigterm(signum, frame):
    stop("terminated (SIGTERM)")  # raises Interrupted here, and again at the next frame if something swallows it


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit code: 0, or 2 for any user mistake, interruption or system refusal (one
    line on stderr, never a traceback)."""
    words = sys.argv[1:3] if argv is None else argv[:2]
    if words[:1] in (["vr"], ["audio"]) or words == ["bench", "vr"]:
        from app.audio_rt.heap import keep_heap

        keep_heap()  # live audio beside a frame loop: before any allocation of note (app/audio_rt/heap.py)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) and argument errors (2, already printed on one line)
        return int(exc.code or 0)
    logging.basicConfig(level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
                        format="sonicverse: %(name)s: %(message)s", stream=sys.stderr)
    if argv is None:  # a crash in a C library (a driver, the GL stack) says where, here and in the workers started
        os.environ.setdefault("PYTHONFAULTHANDLER", "1")
        if not faulthandler.is_enabled():
            faulthandler.enable()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if argv is None else None
    try:
        with stops_quiet_in_finalisers():  # the handler's raise inside a __del__: no "Exception ignored" traceback
            code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not at interpreter exit
        return code
    except SonicverseError as exc:
        print(f"sonicverse: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("sonicverse: error: interrupted", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `sonicverse ... | head`: the reader has gone; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except MemoryError:
        print("sonicverse: error: out of memory: use a smaller scene, a coarser resolution or fewer items",
              file=sys.stderr)
        return 2
    except OSError as exc:  # the system refused a file or device operation (disk full, permissions...)
        where = f": {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"sonicverse: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except Exception as exc:
        stopped = stop_behind(exc)  # SIGTERM's raise, wrapped by Python or a library on its way here
        if stopped is None:
            raise
        print(f"sonicverse: error: {stopped}", file=sys.stderr)
        return stopped.exit_code
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
