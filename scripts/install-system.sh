#!/usr/bin/env bash
# Installs the Debian packages Sonicverse needs (idempotent: does nothing when all are present).
set -euo pipefail
PKGS=(python3 python3-venv python3-dev build-essential libportaudio2 jackd2 libjack-jackd2-0 libsndfile1
      libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libopengl0 libgbm1 xvfb xauth libxcb-cursor0 libxcb-icccm4
      libxcb-keysyms1 libxkbcommon-x11-0 libxcb-image0 libxcb-render-util0 libxcb-xinerama0 libxcb-randr0
      libxcb-shape0 libxcb-xkb1 libfontconfig1 libdbus-1-3 espeak-ng sox rt-tests)
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then exit 0; fi
echo "installing system packages: ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
