"""CLI commands of the acoustic engine: render and bake."""
from __future__ import annotations

import json

import numpy as np

from app.cli import args as A


def cmd_render(a) -> int:
    import soundfile as sf

    from assets_manifest import soundbank
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(a.spec)
    src, lis = a.source, a.listener
    _inside(scene, "--source", src[:3])
    _inside(scene, "--listener", lis[:3])
    cfg = RenderConfig(sample_rate=a.sample_rate, block=a.block, output=a.output,
                       occlusion=not a.no_occlusion, late_reverb=not a.no_reverb)
    sig, sr = soundbank.load_sound(a.sound)
    probes = (scene_probes(scene, BakeConfig(rays=a.rays, scattering=a.scattering, per_room=a.per_room),
                           progress=not a.json)
              if cfg.late_reverb else None)
    r = AcousticRenderer(scene, cfg, probes=probes)
    r.add_source(sig, src, loop=True, sample_rate=sr)
    r.add_listener(lis[:3], lis[3] if len(lis) == 4 else 0.0)
    n = int(round(a.seconds * cfg.sample_rate))
    peak, energy = np.zeros(2), np.zeros(2)
    from sonicverse_core.progress import progress
    from sonicverse_core.storage import atomic_write

    # streamed block by block into a temporary file that replaces the target at the end: memory does not grow
    # with --seconds, and an interrupted render leaves no half-written output
    fmt = "FLAC" if a.out.lower().endswith(".flac") else "WAV"
    with atomic_write(a.out) as fh, sf.SoundFile(fh, "w", cfg.sample_rate, 2, subtype="FLOAT" if fmt == "WAV"
                                                   else "PCM_24", format=fmt) as out:
        done = 0
        for _ in progress(range(-(-n // cfg.block)), desc="rendering", enabled=not a.json and a.seconds > 30):
            y = r.render_block()[0][:, : n - done].astype(np.float64)
            out.write(y.T)
            peak = np.maximum(peak, np.abs(y).max(axis=1))
            energy += np.sum(y * y, axis=1)
            done += y.shape[1]
    res = {"out": a.out, "sample_rate": cfg.sample_rate, "seconds": a.seconds, "peak": peak.tolist(),
           "rms": np.sqrt(energy / max(n, 1)).tolist(), "subsystems": r.subsystems}
    print(json.dumps(res) if a.json else f"wrote {a.out} ({', '.join(r.subsystems)})")
    return 0


def _inside(scene, option: str, p) -> None:
    """A position the user gave must lie within the scene's bounds: the renderer has no ground, sky or outdoor
    space, so a source placed outside the home would render as a faint sound through its walls, and a listener
    there would hear the home from nowhere real."""
    from sonicverse_core.errors import ConfigError

    lo, hi = scene.bounds
    if np.any(np.asarray(p) < lo - 1e-6) or np.any(np.asarray(p) > hi + 1e-6):
        box = " x ".join(f"{a:g}..{b:g}" for a, b in zip(np.round(lo, 2), np.round(hi, 2)))
        raise ConfigError(f"{option} {','.join(f'{x:g}' for x in p)} is outside the scene (x, y, z within {box} m)")


def cmd_bake(a) -> int:
    from sonicverse_core.acoustics.probes import BakeConfig, bake, default_probe_positions
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(a.spec)
    caster = None
    if a.at:
        from sonicverse_core.acoustics.probes import enclosed_fraction
        from sonicverse_core.errors import ConfigError
        from sonicverse_core.geometry.raycast import SceneRayCaster

        positions = np.array(a.at)
        caster = SceneRayCaster(scene)  # one for the enclosure check and the bake
        for p, f in zip(positions, enclosed_fraction(scene, positions, caster=caster)):
            if f <= 0.5:  # outside the enclosure (or the scene is open there): a probe would bake a ray escape
                raise ConfigError(f"--at {','.join(f'{x:g}' for x in p)} is not enclosed by the scene: only "
                                  f"{f:.0%} of the rays from there hit a surface; put probes inside a room")
    else:
        positions = default_probe_positions(scene, a.probes, rng=np.random.default_rng(a.seed))
    probes = bake(scene, positions, BakeConfig(rays=a.rays, seed=a.seed, scattering=a.scattering,
                                               per_room=a.per_room),
                  caster=caster, progress=not a.json)
    if a.json:
        print(json.dumps({"scene": scene.spec, "probes": [p.to_json() for p in probes]}))
    else:
        for p in probes:
            print(f"probe at {np.round(p.position, 2).tolist()}: RT60 (s) {np.round(p.rt60, 2).tolist()}")
    return 0


def add_audio_commands(sub, bench_sub) -> None:
    from app.cli.audio import add_commands
    from sonicverse_core.acoustics.probes import SCATTERING

    def rooms(parser) -> None:
        """Each room's own decay, coupled (the default since session 27), or the decay of the whole connected
        space at every probe (``--whole-space``: the model before it)."""
        g = parser.add_mutually_exclusive_group()
        g.add_argument("--per-room", dest="per_room", action="store_true",
                       help="bake each room's own decay and couple the rooms' decays (each room its own reverb, "
                       "double slopes between rooms; the default)")
        g.add_argument("--whole-space", dest="per_room", action="store_false",
                       help="bake the decay of the whole connected space at every probe (one decay everywhere; the "
                       "default before session 27)")
        parser.set_defaults(per_room=True)

    scattering_help = ("how a bounce scatters in the bake: stochastic (the scattering coefficient as the probability "
                       "of a Lambertian bounce) or vector (blended directions, as pyroomacoustics; default: "
                       "%(default)s)")

    add_commands(sub)
    r = sub.add_parser("render", help="render binaural audio of one source to a file",
                       description="Render a sound at a source position as heard at a listener (binaural).")
    r.add_argument("spec", help="scene spec")
    r.add_argument("--sound", required=True, help="sound bank name (e.g. sofa, sofa/3) or a WAV/FLAC file")
    r.add_argument("--source", required=True, type=A.argtype(A.xyz), help="X,Y,Z of the source (m)")
    r.add_argument("--listener", required=True, type=A.argtype(lambda t: A.xyz(t, (3, 4))),
                   help="X,Y,Z[,YAW] of the listener (m, degrees)")
    r.add_argument("--seconds", type=A.number(0, 24 * 3600, lo_open=True, unit="s"), default=3.0,
                   help="length of the output, s (streamed to disk; default: %(default)s)")
    r.add_argument("--out", required=True, type=A.out_file(".wav", ".flac"), help="output WAV or FLAC file")
    r.add_argument("--sample-rate", type=A.count(8000, 192000), default=48000,
                   help="output sample rate, Hz (default: %(default)s)")
    r.add_argument("--block", type=A.count(16, 8192), default=256, help="frames per block (default: %(default)s)")
    r.add_argument("--output", default="binaural", choices=["binaural", "stereo", "mono"],
                   help="binaural (HRTF), stereo (panned) or mono (default: %(default)s)")
    r.add_argument("--rays", type=A.count(100, 10_000_000), default=2000,
                   help="rays per reverb probe (default: %(default)s)")
    r.add_argument("--scattering", choices=SCATTERING, default="stochastic", help=scattering_help)
    rooms(r)
    r.add_argument("--no-occlusion", action="store_true", help="no transmission loss through walls and doors")
    r.add_argument("--no-reverb", action="store_true", help="no early reflections and no late reverb")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.set_defaults(func=cmd_render)
    b = sub.add_parser("bake", help="bake reverb probes (ray tracing)",
                       description="Bake reverb probes over the scene's static structure; cached on disk.")
    b.add_argument("spec", help="scene spec")
    b.add_argument("--probes", type=A.count(1, 10_000), default=None, help="number of probes spread over the floor "
                   "(default: one per room)")
    b.add_argument("--rays", type=A.count(100, 10_000_000), default=2000,
                   help="rays per probe (default: %(default)s)")
    b.add_argument("--scattering", choices=SCATTERING, default="stochastic", help=scattering_help)
    rooms(b)
    b.add_argument("--at", action="append", type=A.argtype(A.xyz), help="X,Y,Z of a probe (repeatable)")
    b.add_argument("--seed", type=A.seed, default=0, help="seed of the ray directions (default: %(default)s)")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=cmd_bake)

    ba = bench_sub.add_parser("audio", help="per-block cost of the full audio pipeline vs naive convolution",
                              description="Per-block cost of the full pipeline (HRTF, occlusion, early reflections, "
                              "late reverb) with a walking, turning listener, as a fraction of real time, and a "
                              "naive per-source scipy convolution measured in the same run.")
    ba.add_argument("--sources", type=A.count(1, 4096), default=64, help="sources (default: %(default)s)")
    ba.add_argument("--seconds", type=A.number(0.1, 3600, unit="s"), default=8.0,
                    help="audio rendered, s (default: %(default)s)")
    ba.add_argument("--scene", default="builtin:apartment", help="scene spec (default: %(default)s)")
    ba.add_argument("--sample-rate", type=A.count(8000, 192000), default=48000, help="Hz (default: %(default)s)")
    ba.add_argument("--block", type=A.count(16, 8192), default=256, help="frames per block (default: %(default)s)")
    rooms(ba)
    ba.add_argument("--reverb", choices=("convolution", "fdn"), default="convolution",
                    help="late reverb: partitioned convolution (default) or the cheaper FDN")
    ba.add_argument("--er-images", choices=("room", "box"), default="room",
                    help="early reflections off the listener's room's own walls (default) or its probe's box")
    ba.add_argument("--er-order", type=int, choices=(1, 2), default=1,
                    help="early reflections' image-source order (default: %(default)s)")
    from sonicverse_core.acoustics.config import RenderConfig

    ba.add_argument("--neighbour-tails", type=A.count(0, 4), default=RenderConfig.neighbour_tails, metavar="N",
                    help="coupled rooms heard apart besides the slowest mode's (default: %(default)s)")
    ba.add_argument("--tail-partitions", choices=("auto", "uniform"), default=RenderConfig.tail_partitions,
                    help="the convolution tails: long partitions after the first few where a tail spans 64 blocks "
                    "or more (auto), or every partition one block long (default: %(default)s)")
    ba.add_argument("--listener-room", default=None, metavar="NAME",
                    help="start the listener in this room of the scene (default: a random navigable point)")
    ba.add_argument("--walk", type=A.number(0.0, 3.0, unit="m/s"), default=0.15, metavar="M/S",
                    help="the listener's walking speed on its 0.3 m circle, m/s (default: %(default)s; a person "
                    "walking in VR: about 1-1.4)")
    ba.add_argument("--breakdown", action="store_true",
                    help="also report each subsystem's mean share of the block (per_subsystem)")
    ba.add_argument("--door-every", type=A.number(0.01, 3600, unit="s"), default=None, metavar="S",
                    help="every S seconds of audio a door (each in turn) opens or shuts; report the cost of applying "
                    "it and of the three blocks that render it (doors)")
    ba.add_argument("--json", action="store_true", help="(always JSON)")
    ba.set_defaults(func=cmd_bench_audio)
    bc = bench_sub.add_parser("accuracy", help="error vs run time of every accuracy/speed knob",
                              description="Sweep rays per probe, bounces, probes, HRTF interpolation and taps, early "
                              "reflection order, reverb method and block size; print error vs a reference and run "
                              "time per setting, with the Pareto front.")
    bc.add_argument("--plot", type=A.out_file(".png"), help="write a PNG of error vs time per knob")
    bc.add_argument("--reference-rays", type=A.count(1000, 100_000_000), default=1_000_000,
                    help="rays of the reference bake (cached; default: %(default)s)")
    bc.add_argument("--quick", action="store_true", help="fewer settings per knob")
    bc.add_argument("--json", action="store_true", help="(always JSON)")
    bc.set_defaults(func=cmd_bench_accuracy)
    bf = bench_sub.add_parser("fidelity", help="sound between rooms: ours vs pyroomacoustics and theory",
                              description="Shoeboxes, an L-shaped room, two rooms joined by a door (with and "
                              "without line of sight), a dead room beside a live one and a dead hall between two "
                              "live rooms, rendered by us and by pyroomacoustics' hybrid simulator in the same "
                              "run; G, T30, EDT, C50, DRR per octave band 250 Hz-4 kHz, errors against the "
                              "targets, run times, ours over the peer's energy in windows after the direct sound; "
                              "sealed rooms against the mass-law estimate.")
    bf.add_argument("--rays", type=A.count(1000, 10_000_000), default=20_000,
                    help="pyroomacoustics' rays (default: %(default)s)")
    bf.add_argument("--plot", type=A.out_file(".png"), help="write a PNG of ours vs the peer per parameter")
    bf.add_argument("--quick", action="store_true", help="three cases only")
    bf.add_argument("--seed", type=A.seed, default=0, help="seed of the peer's ray tracing (default: %(default)s)")
    bf.add_argument("--scattering", choices=SCATTERING, default="stochastic", help=scattering_help)
    rooms(bf)
    bf.add_argument("--er-order", type=int, choices=(1, 2), default=1,
                    help="our early reflections' image-source order (default: %(default)s)")
    bf.add_argument("--json", action="store_true", help="(always JSON)")
    bf.add_argument("--er-images", choices=("room", "box"), default="room",
                    help="early reflections off the listener's room's own walls (default) or its probe's box")
    bf.add_argument("--realisations", type=A.count(1, 64), default=1,
                    help="run both models N times (other ray seeds, other tail noise) and compare the mean energy "
                    "decays: the models, not one draw of each (default: %(default)s)")
    bf.add_argument("--tail-edt", choices=("on", "off"), default="on",
                    help="our tails fall first at the bake's early decay time, then at its RT60 (on), or at the "
                    "RT60 alone (off) (default: %(default)s)")
    from sonicverse_core.acoustics.config import RenderConfig

    bf.add_argument("--tail-buildup", type=A.number(0.0, 0.2), default=RenderConfig.tail_buildup, metavar="S",
                    help="the late part of a source in another room builds up as 1 - e^(-t / S) (0: off; "
                    "default: %(default)s)")
    bf.add_argument("--tail-beam", type=A.number(0.0, 1.0), default=RenderConfig.tail_beam, metavar="P",
                    help="the share of that late part that builds up as 1 - e^(-t / S), the rest at the coupled "
                    "rooms' own rate (1: all at S, the model before session 61; default: %(default)s)")
    bf.add_argument("--neighbour-tails", type=A.count(0, 4), default=RenderConfig.neighbour_tails, metavar="N",
                    help="coupled rooms heard apart besides the slowest mode's (default: %(default)s)")
    bf.add_argument("--reverb", choices=("convolution", "fdn"), default="convolution",
                    help="our late reverb: partitioned convolution (default) or the cheaper FDN")
    bf.add_argument("--min-scattering", type=A.number(0.0, 1.0), default=0.0, metavar="S",
                    help="every material scatters at least S in both models (1: every bounce Lambertian in "
                    "both, one reflection law, so what is left is the rest of the models; no sealed rooms; "
                    "default: %(default)s)")
    bf.add_argument("--case", metavar="TEXT", default=None,
                    help="only the cases whose name contains TEXT (e.g. 'hall', 'shoebox')")
    bf.set_defaults(func=cmd_bench_fidelity)
    bq = bench_sub.add_parser("cues", help="does what the robot hears point where it should go? (AudioGoal homes)",
                              description="At AudioGoal episodes' starts in train homes, facing random ways: the "
                              "share of places whose interaural level and time differences point to the source's "
                              "side (line of sight) or to the side of the last bend of the open path to it (the "
                              "doorway: no line of sight), per acoustic model (paths alone, + early reflections, + "
                              "the whole space's late reverb, + per-room late reverb) in the same run, with the "
                              "paths' level against the whole output and each model's cost. Chance is 0.5.")
    bq.add_argument("--episodes", type=A.count(1, 100_000), default=40, help="episodes (default: %(default)s)")
    bq.add_argument("--headings", type=A.count(1, 64), default=3,
                    help="random headings per place (default: %(default)s)")
    bq.add_argument("--seconds", type=A.number(1.05, 30.0), default=2.0,
                    help="seconds rendered; the last one is analysed (default: %(default)s)")
    bq.add_argument("--seed", type=A.seed, default=0, help="seed of the episodes and headings (default: %(default)s)")
    bq.add_argument("--json", action="store_true", help="(always JSON)")
    bq.set_defaults(func=cmd_bench_cues)


def cmd_bench_audio(a) -> int:
    from app.bench.engine import bench_audio

    print(json.dumps(bench_audio(a.sources, a.seconds, a.scene, sample_rate=a.sample_rate, block=a.block,
                                 per_room=a.per_room, reverb=a.reverb, er_images=a.er_images,
                                 er_order=a.er_order, neighbour_tails=a.neighbour_tails,
                                 listener_room=a.listener_room, walk=a.walk, tail_partitions=a.tail_partitions,
                                 breakdown=a.breakdown, door_every=a.door_every)))
    return 0


def cmd_bench_accuracy(a) -> int:
    from app.bench.accuracy import bench_accuracy

    print(json.dumps(bench_accuracy(a.reference_rays, a.quick, a.plot)))
    return 0


def cmd_bench_fidelity(a) -> int:
    from app.bench.fidelity import bench_fidelity

    print(json.dumps(bench_fidelity(a.rays, a.plot, a.quick, a.seed, a.scattering, a.er_order, a.per_room,
                                    a.er_images, a.realisations, a.tail_edt == "on", a.tail_buildup,
                                    a.neighbour_tails, a.case, a.reverb, a.tail_beam, a.min_scattering)))
    return 0


def cmd_bench_cues(a) -> int:
    from app.bench.cues import bench_cues

    print(json.dumps(bench_cues(a.episodes, a.headings, a.seconds, a.seed)))
    return 0
