#!/usr/bin/env bash
# Peak resident memory of `scanrig scan` per method: each shipped rig at its own settings and, for
# the voxel methods, at 512^3 (the rig's `resolution = 128` raised to 512 in a temporary copy).
# Measured with GNU time (`/usr/bin/time -v`, "Maximum resident set size") on the release binary.
# Prints `method | settings | MiB` lines for `benches/perf_table.py --rss FILE`.
#
# Usage: cargo build --release && benches/peak_rss.sh [RIG ...] > target/peak-rss.txt
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/scanrig
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
rigs=("$@")
if [ ${#rigs[@]} -eq 0 ]; then
  rigs=(simulated shadow-carving space-carving-photo voxel-coloring depth-fusion structured-light structured-light-phase laser)
fi
measure() { # rig-file label settings
  local log="$tmp/time.log"
  if /usr/bin/time -v "$bin" scan --rig "$1" --out "$tmp/out" >/dev/null 2>"$log"; then
    local kb
    kb=$(sed -n 's/.*Maximum resident set size (kbytes): //p' "$log")
    echo "$2 | $3 | $((kb / 1024))"
  else
    echo "$2 | $3 | failed: $(grep -v '^\s' "$log" | tail -1)"
  fi
  rm -rf "$tmp/out"
}
for r in "${rigs[@]}"; do
  f="config/rigs/$r.toml"
  measure "$f" "$r" "shipped ($(grep -m1 -o 'resolution = [0-9]*' "$f" | grep -o '[0-9]*')^3)"
  if [ -n "${RSS_512:-1}" ] && grep -q '^resolution = 128' "$f"; then
    sed 's/^resolution = 128/resolution = 512/' "$f" > "$tmp/$r-512.toml"
    measure "$tmp/$r-512.toml" "$r" "512^3"
  fi
done
