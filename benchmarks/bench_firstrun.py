"""First run against second run: what a new user (or a fresh CI machine) waits for while numba
compiles voxtool's kernels, command by command, with and without `voxtool compile` at install.

    python benchmarks/bench_firstrun.py [--source SCANS] [--out bench-results/firstrun.json]

Three runs of the same commands (build, encode zstd, encode cm, merge, export .mcap, in the order
a new user meets them), each with numba's cache in its own folder (NUMBA_CACHE_DIR):
- first run: the cache empty, so each command compiles what no command before it did, as on a
  fresh clone that skipped `voxtool compile`;
- after compile: a new empty cache, `voxtool compile` (timed apart), then the commands, as on a
  fresh clone installed with the README's first command;
- second run: the commands again on the first run's cache.
Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path


def commands(source: list[str], d: Path) -> list[tuple[str, list[str]]]:
    return [
        ("build", ["build", *source, "-o", str(d / "map.vxm")]),
        ("encode --codec zstd", ["encode", *source, "-o", str(d / "z.mcap"), "--codec", "zstd"]),
        ("encode --codec cm", ["encode", *source, "-o", str(d / "c.mcap"), "--codec", "cm"]),
        ("merge", ["merge", str(d / "z.mcap"), "-o", str(d / "fused.vxm")]),
        ("export .mcap", ["export", str(d / "map.vxm"), "-o", str(d / "map.mcap")]),
    ]


def timed(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(["voxtool", *cmd, "--no-progress"], check=True, capture_output=True, env=env)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=None, help="scans to use instead of the shipped sample (--sample)")
    ap.add_argument("--out", default="bench-results/firstrun.json")
    args = ap.parse_args()
    source = [args.source] if args.source else ["--sample"]
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        fresh = {**os.environ, "NUMBA_CACHE_DIR": str(d / "cache-first")}
        ahead = {**os.environ, "NUMBA_CACHE_DIR": str(d / "cache-compiled")}
        compile_s = timed(["compile"], ahead)
        times: dict[str, list[float]] = {}
        for env in (fresh, ahead, fresh):  # first run, after `voxtool compile`, second run
            for name, cmd in commands(source, d):
                times.setdefault(name, []).append(timed(cmd, env))
    rows = [{"command": name, "first_s": round(first, 2), "after_compile_s": round(after, 2),
             "second_s": round(second, 2)} for name, (first, after, second) in times.items()]
    print(f"{'command':<22} {'first run':>9} {'after compile':>13} {'second run':>10}")
    for r in rows:
        print(f"{r['command']:<22} {r['first_s']:>8.2f}s {r['after_compile_s']:>12.2f}s {r['second_s']:>9.2f}s")
    total = [sum(r[k] for r in rows) for k in ("first_s", "after_compile_s", "second_s")]
    print(f"{'all five':<22} {total[0]:>8.2f}s {total[1]:>12.2f}s {total[2]:>9.2f}s")
    print(f"voxtool compile (once, at install): {compile_s:.2f}s")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"source": source, "compile_s": round(compile_s, 2), "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
