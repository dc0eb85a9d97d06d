#!/bin/bash
# A lent machine's live-audio check (issue 17: each task in the VR loop with live audio on a JACK dummy server for
# 60 s, 0 xruns), for a machine with Python 3.12 and no registry. Beside this repository's root it needs:
#   .whl      the project's wheels that the machine lacks, for cp312 (`pip download --no-deps --only-binary=:all:
#             --python-version 3.12 ...`): sounddevice cffi pycparser pyFFTW soundfile pyrender trimesh embreex
#             rtree pyglet freetype-py gymnasium Farama-Notifications platformdirs slab (its KEMAR file), and
#             PyOpenGL 3.1.10 (3.1.0 fails under Python 3.12: "No array-type handler for type _ctypes.type")
#   .jack     jackd2, PortAudio, rt-tests and their libraries as Debian .deb files (`apt-get download`)
#   .gl       the GL loaders as .deb files
#   .svcache  a cache filled here by the same commands run with SONICVERSE_CACHE=$PWD/.svcache (the HRTF, bakes,
#             looks; speech too if a run says any: there is no espeak-ng there)
# The tree must stay under the tool's 64 MiB: untrack the checkpoints this needs not (agents/checkpoints/*.pt but
# sound-localizer.pt) for the call, and ignore them in .git/info/exclude; restore both afterwards.
# Usage: scripts/device/bench_vr.sh [SECONDS] [TASK:AGENT[:JACK_PERIOD[:ROLES]] | audio:SOURCES ...] (the period 256
# unless given: 256, 512 or 1024 frames; ROLES sets SONICVERSE_RT_NICE for the run: the threads that take nice values
# where real time is refused, e.g. callback,server or none); one JSON line per run in
# $OUT/bench_vr.jsonl (audio:N runs `bench audio --sources N` into $OUT/bench_audio.jsonl).
cd "$(dirname "$0")/../.."
. scripts/device/lent.sh .jack .svcache  # (it unpacks packages into /: for a lent machine only)
SECS=${1:-60}; shift || true
RUNS=${*:-"orientation-training:simulated speaker-following:scripted speaker-following:scripted voice-retrieval:scripted"}
mkdir -p /opt/jk && for f in .jack/*.deb; do dpkg -x "$f" /opt/jk; done
printf "/opt/jk/usr/lib/x86_64-linux-gnu\n/opt/jk/lib/x86_64-linux-gnu\n" > /etc/ld.so.conf.d/zz-sonicverse-jack.conf
ldconfig
export PATH=/opt/jk/usr/bin:$PATH JACK_DRIVER_DIR=/opt/jk/usr/lib/x86_64-linux-gnu/jack
export ALSA_CONFIG_PATH=/opt/jk/usr/share/alsa/alsa.conf
nproc; uname -r; cat /proc/self/cgroup; cat /sys/fs/cgroup/cpu.max 2>/dev/null; cat /proc/pressure/cpu 2>/dev/null
cat /sys/kernel/mm/transparent_hugepage/enabled 2>/dev/null; cat /sys/devices/system/cpu/cpu0/cpufreq/scaling_governor 2>/dev/null
grep -m1 "model name" /proc/cpuinfo; grep -o -w -E "avx2|avx512f|fma" /proc/cpuinfo | sort -u | xargs
python3 -c "import sys, numpy, numba; print(sys.version.split()[0], numpy.__version__, numba.__version__)"
command -v jackd cyclictest || exit 4
python3 -c "from app.audio_rt import sched; print('SCHED_FIFO allowed:', sched.fifo_allowed(), '; nice -20 allowed:',
            sched.nice_allowed(-20))"
python3 -c "import sounddevice as sd; print(sd.get_portaudio_version()[1])" || exit 5
T0=$SECONDS
for r in $RUNS; do
  t=${r%%:*}; a=${r#*:}; per=256; unset SONICVERSE_RT_NICE
  case $a in *:*:*) export SONICVERSE_RT_NICE=${a##*:}; a=${a%:*};; esac  # a fourth field: the threads niced
  case $a in *:*) per=${a#*:}; a=${a%%:*};; esac
  if [ "$t" = audio ]; then  # the renderer alone, offline: compares a core's speed with this VM's
    python3 -m app.cli bench audio --sources "$a" --seconds 8 --json | tee -a "$OUT/bench_audio.jsonl" | cut -c1-600
    continue
  fi
  timeout $((SECS + 120)) python3 -m app.cli bench vr --task "$t" --agent "$a" --audio-seconds "$SECS" \
    --jack-period "$per" > /tmp/vr.json 2> /tmp/vr.err
  rc=$?
  echo "$t $a $per nice=${SONICVERSE_RT_NICE-all} rc $rc at $((SECONDS - T0)) s"; tail -3 /tmp/vr.err | cut -c1-300
  python3 - "$rc" <<'PY' | tee -a "$OUT/bench_vr.jsonl"
import json, os, sys
try:
    b = json.load(open("/tmp/vr.json"))
except (OSError, ValueError):
    print(json.dumps({"rc": int(sys.argv[1]), "error": open("/tmp/vr.err").read()[-400:]})); sys.exit()
p = b.get("platform", {})
print(json.dumps({"rt_nice": os.environ.get("SONICVERSE_RT_NICE", "all")}
                 | {k: b.get(k) for k in ("task", "agent", "jack_period", "loop_fps", "xruns", "xrun_blocks", "cycle_blocks",
                                          "callbacks", "xrun_at_s", "xrun_callback_ms", "xrun_callback_cpu_ms",
                                          "callback_ms", "callback_cpu_ms", "callback_errors")}
                 | {k: p.get(k) for k in ("supervisor_scheduling", "callback_scheduling", "jack_scheduling",
                                          "probe_scheduling", "wakeup_ms_max", "steal_ms",
                                          "platform_stalls", "xruns_in_platform_stalls", "xruns_callback_overran",
                                          "xruns_callback_held_off", "xruns_unexplained", "cpus_busy",
                                          "cpu_pressure_ms", "cgroup_throttled", "cgroup_throttled_ms",
                                          "cgroup_cpu_max", "threads_top_cpus", "why")}))
PY
  [ $rc -eq 0 ] || exit 6  # the rest would fail alike: keep the device time for a rerun
done
