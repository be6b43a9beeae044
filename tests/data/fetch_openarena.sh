#!/usr/bin/env bash
# Fetch Debian's openarena-081-maps (50 Quake 3 arenas, GPL-2+) without a root install.
# Result: artifacts/data/openarena/pak1-maps.pk3 (tests look there, or at $NAVI_OPENARENA_PK3).
set -euo pipefail
cd "$(dirname "$0")/../.."
dest=artifacts/data/openarena
[ -f "$dest/pak1-maps.pk3" ] && exit 0
mkdir -p "$dest" && tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
( cd "$tmp" && { apt-get download openarena-081-maps 2>/dev/null || { apt-get update -qq && apt-get download openarena-081-maps; }; } )
dpkg -x "$tmp"/openarena-081-maps_*.deb "$tmp/x"
pk3=$(find "$tmp/x" -name 'pak1-maps.pk3' | head -n 1)
[ -n "$pk3" ] || { echo "pak1-maps.pk3 not found in the package" >&2; exit 1; }
cp "$pk3" "$dest/pak1-maps.pk3"
echo "[data] $dest/pak1-maps.pk3 ($(du -h "$dest/pak1-maps.pk3" | cut -f1))"
