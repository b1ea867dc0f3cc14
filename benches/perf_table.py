#!/usr/bin/env python3
"""Regenerate the README's performance table from bench output.

Usage (one command, from the repository root):
    python3 benches/perf_table.py --run          # runs `cargo bench --bench photo --bench methods` and
                                                 # benches/scan_figures.sh, keeps their output in
                                                 # target/perf-bench.log and target/scan-figures.txt,
                                                 # rewrites README.md
    python3 benches/perf_table.py LOG [LOG ...] [--scans FILE]  # rebuild the table from saved output

Every `PERF {json}` line the benches print becomes one row: method, case, our time (and rate when
the figure is a throughput), the baseline or peer and its time from the same run, and the ratio.
The table goes between the README's `<!-- perf-table:begin -->` and `<!-- perf-table:end -->`
markers, with the machine's core count and load averages before and after the run. The whole-scan
rows (peak RSS, seconds after the last frame, total) come from `--scans FILE`, the lines
`method | settings | MiB | after-last-frame s (median) | fastest | slowest | total s (median) | runs`
that benches/scan_figures.sh prints.
"""

import argparse
import json
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BEGIN, END = "<!-- perf-table:begin -->", "<!-- perf-table:end -->"


def loadavg():
    try:
        with open("/proc/loadavg") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "unknown"


def fmt_time(s):
    if s is None:
        return "-"
    if s >= 1.0:
        return f"{s:.2f} s"
    if s >= 0.9995e-3:
        return f"{s * 1e3:.1f} ms"
    return f"{s * 1e6:.0f} us"


def rows_from(text):
    rows = []
    for line in text.splitlines():
        m = re.match(r"^PERF (\{.*\})\s*$", line)
        if m:
            rows.append(json.loads(m.group(1)))
    return rows


def table(rows, load_before, load_after, cores, scans):
    out = [
        f"Measured on {cores} cores; load average (1, 5, 15 min) {load_before} before the run and {load_after} "
        "after it (ratios come from one run, both sides under the same load; against an external peer, "
        "ours and the peer alternate in three rounds and the ratio is the median of the rounds' ratios).",
        "",
        "| method | case | ours | baseline or peer (same run) | theirs | ratio |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        ours = fmt_time(r["ours_s"])
        if r.get("rate"):
            ours += f" ({1.0 / r['ours_s']:.0f} {r['rate']})"
        peer = r.get("peer") or "none measured"
        ratio = f"{r['ratio']:.1f}x" if r.get("ratio") else "-"
        out.append(f"| {r['method']} | {r['case']} | {ours} | {peer} | {fmt_time(r.get('peer_s'))} | {ratio} |")
    if scans:
        out += [
            "",
            "Whole scans through `scanrig scan` on the simulated rigs (`benches/scan_figures.sh`, same run; "
            "each setting scanned the number of times shown, one after the other, the median given with the "
            "fastest and slowest run; peak RSS is the largest of the runs):",
            "",
            "| method | settings | peak RSS | after the last frame: median (fastest-slowest) | whole scan: median | runs |",
            "|---|---|---|---|---|---|",
        ]
        for line in scans:
            parts = [p.strip() for p in line.split("|")]
            if len(parts) == 8:
                name, settings, mib, median, fastest, slowest, total, runs = parts
                after = f"{median} s" if runs == "1" else f"{median} s ({fastest}-{slowest})"
                out.append(f"| {name} | {settings} | {mib} MiB | {after} | {total} s | {runs} |")
            elif len(parts) == 3:
                out.append(f"| {parts[0]} | {parts[1]} | {parts[2]} | - | - | - |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("logs", nargs="*")
    ap.add_argument("--run", action="store_true", help="run the benches first")
    ap.add_argument("--scans", help="output of benches/scan_figures.sh")
    ap.add_argument("--readme", default=os.path.join(ROOT, "README.md"))
    a = ap.parse_args()
    before = loadavg()
    text = ""
    if a.run:
        log = os.path.join(ROOT, "target", "perf-bench.log")
        with open(log, "w") as f:
            subprocess.run(["cargo", "bench", "--bench", "photo", "--bench", "methods"], cwd=ROOT, stdout=f, check=True)
        a.logs.append(log)
        a.scans = os.path.join(ROOT, "target", "scan-figures.txt")
        with open(a.scans, "w") as f:
            subprocess.run([os.path.join(ROOT, "benches", "scan_figures.sh")], cwd=ROOT, stdout=f, check=True)
    for p in a.logs:
        with open(p) as f:
            text += f.read() + "\n"
    m = re.search(r"load average ([\d.]+ [\d.]+ [\d.]+)", text)
    if m and not a.run:
        before = m.group(1)
    rows = rows_from(text)
    if not rows:
        sys.exit("no PERF lines in the bench output")
    scans = open(a.scans).read().splitlines() if a.scans else []
    body = table(rows, before, loadavg(), os.cpu_count(), scans)
    with open(a.readme) as f:
        readme = f.read()
    if BEGIN not in readme or END not in readme:
        sys.exit(f"{a.readme} has no {BEGIN} ... {END} markers")
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    with open(a.readme, "w") as f:
        f.write(head + BEGIN + "\n" + body + "\n" + END + tail)
    print(body)


if __name__ == "__main__":
    main()
