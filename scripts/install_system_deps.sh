#!/usr/bin/env bash
# Installs the Debian packages for offscreen MuJoCo rendering (EGL/OSMesa on Mesa llvmpipe)
# when they are missing and we are allowed to (root with apt-get). Never fails the build:
# state-mode work runs without them, and pixel tests report the missing renderer themselves.
set -u
pkgs=(libegl1 libgl1-mesa-dri libosmesa6)
missing=()
for p in "${pkgs[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "installing ${missing[*]} for offscreen rendering"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}") \
    || echo "warning: could not install ${missing[*]}; pixel rendering may not work"
else
  echo "warning: missing ${missing[*]} (need root + apt-get); pixel rendering may not work"
fi
exit 0
