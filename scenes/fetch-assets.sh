#!/usr/bin/env bash
# Brings the real test assets from Debian packages into ./assets (git-ignored), without
# installing anything: `apt-get download` + `dpkg-deb` extraction.
#   assets/gltf2/    glTF 2.0 test models of assimp-testmodels, deliberately broken ones included
#   assets/dungeon/  castle-game-engine-doc's third_person_navigation level (level-dungeon.gltf)
# Idempotent: does nothing when the assets are already there.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
dest="$root/assets"
if [ -f "$dest/gltf2/.complete" ] && [ -f "$dest/dungeon/.complete" ]; then
  echo "assets already in $dest"
  exit 0
fi
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"
if ! apt-get download assimp-testmodels castle-game-engine-doc >/dev/null 2>&1; then
  echo "apt-get download failed; refreshing package lists (needs root) and retrying" >&2
  apt-get update -q >/dev/null
  apt-get download assimp-testmodels castle-game-engine-doc
fi
mkdir -p x "$dest/gltf2" "$dest/dungeon"
dpkg-deb --fsys-tarfile assimp-testmodels_*.deb | tar -x -C x './usr/share/assimp/models/glTF2'
dpkg-deb --fsys-tarfile castle-game-engine-doc_*.deb | tar -x -C x \
  './usr/share/doc/castle-game-engine-doc/examples/third_person_navigation/data/level'
cp -r x/usr/share/assimp/models/glTF2/. "$dest/gltf2/"
cp -r x/usr/share/doc/castle-game-engine-doc/examples/third_person_navigation/data/level/. "$dest/dungeon/"
# Debian compresses some files; glTF readers need them plain.
find "$dest" -name '*.gz' -exec gunzip -f {} +
touch "$dest/gltf2/.complete" "$dest/dungeon/.complete"
echo "assets ready in $dest"
