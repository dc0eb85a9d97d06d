# Sourced by the lent-machine scripts beside it (`. scripts/device/lent.sh DIR ...` from the repository root): refuses
# to run anywhere but a lent device machine (it unpacks packages into / and installs wheels), checks that the folders
# the script needs lie beside the root (.whl and .gl always, then DIR ...), unpacks the GL loaders, installs the
# project's wheels into /tmp/site and sets the environment the project runs with there (EGL on NVIDIA's driver, the
# warm cache in .svcache, unbuffered output).
[ "${SV_LENT_MACHINE:-}" = 1 ] && [ -n "${OUT:-}" ] || {
  echo "$0: for a lent device machine only: run it there as SV_LENT_MACHINE=1 $0 (with \$OUT set)" >&2; exit 2; }
for d in .whl .gl "$@"; do
  [ -d "$d" ] || { echo "$0: $d/ is missing beside the repository root (see the header)" >&2; exit 2; }
done
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  || exit 3
sed -i "s/np.infty/np.inf/g" /tmp/site/pyrender/*.py
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 PYOPENGL_PLATFORM=egl PYGLET_HEADLESS=1 SONICVERSE_CACHE=$PWD/.svcache
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$__EGL_VENDOR_LIBRARY_FILENAMES" ] || unset __EGL_VENDOR_LIBRARY_FILENAMES
