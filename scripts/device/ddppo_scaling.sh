#!/bin/bash
# A GPU machine's checks (session 24), for a machine with the CUDA torch and no registry: the project's other wheels
# in .whl, the GL loaders' .deb files in .gl and a warm cache in .svcache (all beside this repository's root);
# results in $OUT.
# Checks: DD-PPO frames/s against processes (CPU gloo; CUDA on one shared GPU), the GPU tests,
# bench train's av-nav rows.
cd "$(dirname "$0")/../.."
. scripts/device/lent.sh .svcache  # (it unpacks packages into /: for a lent machine only)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc
python3 -c "import sys, torch; print(sys.version.split()[0], torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
summ() {  # K device wall -> one JSON line from the run's log.csv
python3 - "$@" <<'PY'
import csv, json, sys
k, dev, wall, d = sys.argv[1:5]
try:
    rows = list(csv.DictReader(open(f"{d}/log.csv")))
except OSError:
    print(json.dumps({"nproc": int(k), "device": dev, "error": "no log"})); sys.exit()
f = [int(r["frames"]) for r in rows]; w = [float(r["wall_s"]) for r in rows]
steady = (f[-1] - f[1]) / max(w[-1] - w[1], 1e-9) if len(rows) > 2 else None
print(json.dumps({"nproc": int(k), "device": dev, "updates": len(rows), "frames": f[-1], "train_wall_s": w[-1],
                  "command_s": int(wall), "steady_frames_per_s": round(steady, 1) if steady else None,
                  "rollout_fps_rank0": [float(r["rollout_fps"]) for r in rows]}))
PY
}
run() {  # K device
  local K=$1 dv=$2 S=$SECONDS
  timeout 90 python3 -m app.cli train --recipe ppo --init agents/checkpoints/av-nav_AudioGoal_oracle.pt --nproc $K --envs 2 \
    --frames $((K * 2 * 64 * 6)) --val-episodes 0 --seed 0 --device $dv --out /tmp/pp_${K}_$dv --json > /tmp/pp_${K}_$dv.out 2> /tmp/pp_${K}_$dv.err
  echo "ppo nproc $K $dv rc $?" >&2; tail -2 /tmp/pp_${K}_$dv.err | cut -c1-300 >&2
  summ $K $dv $((SECONDS - S)) /tmp/pp_${K}_$dv | tee -a $OUT/ddppo.jsonl
}
T0=$SECONDS
for K in 1 4 8 16; do run $K cpu; done
run 1 cuda; run 4 cuda
echo "ddppo done at $((SECONDS - T0)) s"
timeout 170 python3 -m pytest -q -p no:cacheprovider -o addopts="" -p no:randomly tests/test_cuda.py 2>&1 | tail -15 | tee $OUT/pytest_cuda.txt
echo "pytest done at $((SECONDS - T0)) s"
if [ $((SECONDS - T0)) -lt 420 ]; then
  timeout 100 python3 -m app.cli bench train --steps 300 --workers 1 16 --agents av-nav --devices cpu cuda > $OUT/bench_train.json 2> $OUT/bench_train.err
  echo "bench rc $? at $((SECONDS - T0)) s"
  python3 -c "import json; b=json.load(open('$OUT/bench_train.json')); print(json.dumps({k: b.get(k) for k in ('device_name','cores','update_speedup','rollout_speedup','vector_vs_one_process')}))"
fi
