#!/usr/bin/env bash
# Whole scans through the real binary on the simulated rigs, one per method at its shipped settings,
# space carving also at 256^3 (where its wait target is stated) and, for the voxel methods, at 512^3
# (the rig's `resolution = 128` raised in a temporary copy): peak resident memory (GNU time's
# "Maximum resident set size", `/usr/bin/time -v`) and, from the scan's report.json, how long the
# user waits after the last frame (`after_last_frame_s`: the last frame captured -> every result on
# disk) and the whole scan (`total`). The simulated rig renders frames as fast as it can (no settle
# or exposure time), so the scan's total is mostly compute; `after_last_frame_s` is the figure a
# real rig's user waits for.
# Each setting below 512^3 is scanned RUNS times (default 3; one after the other) and reported by
# its median, with the fastest and slowest run: on a shared virtual machine one scan's wait moves by
# a tenth of a second or more from run to run. The 512^3 scans run once (they take minutes when the
# budget is raised). The peak RSS is the largest of the runs.
# Prints `method | settings | MiB | after-last-frame s (median) | fastest | slowest | total s
# (median) | runs` lines for `benches/perf_table.py --scans FILE`. RSS_512= (empty) skips the 512^3
# runs. With BUDGET_512=MB set, a 512^3 scan that the rig's memory budget refuses is shown refused
# and then measured with `memory_budget_mb` raised to that many MB (these scans take minutes each
# and need up to about 11 GB; the README's figures were taken with BUDGET_512=16000 on a 24 GB
# machine).
#
# Usage: cargo build --release && benches/scan_figures.sh [RIG ...] > target/scan-figures.txt
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/scanrig
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
rigs=("$@")
if [ ${#rigs[@]} -eq 0 ]; then
  rigs=(simulated shadow-carving space-carving-photo voxel-coloring depth-fusion structured-light structured-light-phase laser)
fi
measure() { # rig-file label settings [runs]
  local log="$tmp/time.log" runs=${4:-${RUNS:-3}} kb=0 afters=() totals=()
  for ((i = 0; i < runs; i++)); do
    if /usr/bin/time -v "$bin" scan --rig "$1" --out "$tmp/out" >/dev/null 2>"$log"; then
      local k after total
      k=$(sed -n 's/.*Maximum resident set size (kbytes): //p' "$log")
      if ((k > kb)); then kb=$k; fi
      read -r after total < <(python3 -c 'import json,sys; t=json.load(open(sys.argv[1]))["timings_s"]; print(t["after_last_frame_s"], t["total"])' "$tmp/out/report.json")
      afters+=("$after")
      totals+=("$total")
      rm -rf "$tmp/out"
    else
      # The scan's own error (for a grid above the memory budget: the estimate), not time's exit line.
      local err
      err=$(grep -v -e $'^\t' -e '^Command exited' "$log" | tail -1 | sed 's/^ *//')
      if [[ $err =~ needs\ about\ ([0-9]+)\ MB.*memory\ budget\ of\ ([0-9]+)\ MB ]]; then
        err="refused: needs about ${BASH_REMATCH[1]} MB, above the memory budget of ${BASH_REMATCH[2]} MB (\`reconstruction.memory_budget_mb\`)"
      else
        err="failed: $err"
      fi
      echo "$2 | $3 | $err"
      rm -rf "$tmp/out"
      return
    fi
  done
  python3 - "$2" "$3" "$kb" "${afters[*]}" "${totals[*]}" <<'PY'
import statistics, sys
label, settings, kb, afters, totals = sys.argv[1:]
a = [float(x) for x in afters.split()]
t = [float(x) for x in totals.split()]
print(f"{label} | {settings} | {int(kb) // 1024} | {statistics.median(a):.3f} | {min(a):.3f} | {max(a):.3f} | {statistics.median(t):.2f} | {len(a)}")
PY
}
raised() { # rig-file rig resolution: a copy of the rig at that resolution; prints its path
  local out="$tmp/$2-$3.toml"
  sed "s/^resolution = 128/resolution = $3/" "$1" > "$out"
  echo "$out"
}
for r in "${rigs[@]}"; do
  f="config/rigs/$r.toml"
  measure "$f" "$r" "shipped ($(grep -m1 -o 'resolution = [0-9]*' "$f" | grep -o '[0-9]*')^3)"
  grep -q '^resolution = 128' "$f" || continue
  # The issue's wait target for space carving is stated at 256^3: its rig is measured there too.
  if [ "$(grep -m1 -o '^method = "[a-z-]*"' "$f")" = 'method = "space-carving"' ]; then
    measure "$(raised "$f" "$r" 256)" "$r" "256^3"
  fi
  if [ -n "${RSS_512-1}" ]; then
    line=$(measure "$(raised "$f" "$r" 512)" "$r" "512^3" 1)
    echo "$line"
    if [[ $line == *"refused: needs about"* ]] && [ -n "${BUDGET_512-}" ]; then
      budget=$BUDGET_512
      sed "s/^\[reconstruction\]\$/[reconstruction]\nmemory_budget_mb = $budget/" "$tmp/$r-512.toml" > "$tmp/$r-512-raised.toml"
      measure "$tmp/$r-512-raised.toml" "$r" "512^3, budget raised to $budget MB" 1
    fi
  fi
done
