#!/bin/bash
# A GPU machine's check (session 53), for a machine with the CUDA torch and no registry: the project's other wheels
# in .whl, the GL loaders' .deb files in .gl and a warm cache in .svcache (all beside this repository's root; the
# header of bench_vr.sh says how to fill them); results in $OUT. The tree must stay under the tool's 64 MiB:
# untrack agents/checkpoints/*.pt (none is needed here) for the call and ignore them in .git/info/exclude; restore
# both afterwards.
# Runs the GPU tests (tests/test_cuda.py, `make test-gpu`'s) on the code as it is, then `bench train` with each model
# on both devices (frames/s of the rollout and the update).
# Usage: SV_LENT_MACHINE=1 scripts/device/gpu_tests.sh [BENCH_LIMIT_S]
cd "$(dirname "$0")/../.."
. scripts/device/lent.sh .svcache  # (it unpacks packages into /: for a lent machine only)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader; nproc
python3 -c "import sys, numpy, torch; print(sys.version.split()[0], numpy.__version__, torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
T0=$SECONDS
timeout 240 python3 -m pytest -q -p no:cacheprovider -o addopts="" tests/test_cuda.py 2>&1 | tail -25 | tee $OUT/pytest_cuda.txt
echo "pytest done at $((SECONDS - T0)) s"
timeout ${1:-200} python3 -m app.cli bench train --steps 300 --workers 1 16 --agents av-nav savi multitask \
  --devices cpu cuda > $OUT/bench_train.json 2> $OUT/bench_train.err
echo "bench rc $? at $((SECONDS - T0)) s"; tail -3 $OUT/bench_train.err | cut -c1-300
python3 -c "import json; b=json.load(open('$OUT/bench_train.json')); print(json.dumps({k: b.get(k) for k in ('device_name','cores','update_speedup','rollout_speedup')}))"
