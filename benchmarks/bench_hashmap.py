"""Hash-map backend on quick_shack (Livox Avia, the sensor of the seed's Urban set): a Table-I
style row per setting, and the relayed map built only from the shared frames.

    python benchmarks/bench_hashmap.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np


def run(src: Path, n_lim: int, share: Path | None) -> dict:
    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.sources import SourceOptions

    return build_map(src, SourceOptions(), MapParams(0.1), SensorModel(), "hashmap", None, False,
                     {"n_lim": n_lim, "d_inf": 0.2}, share)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--out", default="bench-results/hashmap.json")
    args = ap.parse_args()
    src = Path(args.data) / "quick_shack" / "quick_shack.mcap"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n_lim in (50_000, -1):
            share = Path(tmp) / f"share_{n_lim}.mcap"
            r = run(src, n_lim, share)
            row = {"setup": f"n_lim={n_lim if n_lim >= 0 else 'inf'}", "d_inf": 0.2, "n_occ": r["n_occ"],
                   "n_inf_mean": r["per_scan_n_inf"]["mean"], "t_tot_ms": r["per_scan_t_tot_ms"],
                   "t_occ_ms": r["per_scan_t_occ_ms"]["mean"], "t_inf_ms": r["per_scan_t_inf_ms"]["mean"],
                   "t_m_ms": r["per_scan_t_m_ms"]["mean"], "memory_max_mb": round(r["per_scan_memory_bytes"]["max"] / 1e6, 1),
                   "scan_latency_ms": r["scan_latency_ms"], "points_per_scan": round(r["points"] / r["scans"])}
            from voxtool.codec.logstats import log_stats
            from voxtool.codec.share import relay
            from voxtool.config import MapParams, SensorModel
            from voxtool.maps.hashmap import HashVoxelMap

            st = log_stats(share)["robots"]["r1"]
            row.update(shared_avg_Bps=st["avg_Bps"], raw_sensor_Bps=st["raw_sensor_Bps"],
                       bandwidth_reduction=round(1 - st["avg_Bps"] / st["raw_sensor_Bps"], 5))
            if n_lim < 0:
                # relayed map: a second hash map built only from the shared frames
                from voxtool.maps import make_backend
                from voxtool.pipeline import build
                from voxtool.sources import SourceOptions, open_source

                sender = make_backend("hashmap", MapParams(0.1), SensorModel(), n_lim=-1, d_inf=0.2)
                build(open_source(src, SourceOptions()), sender, progress=False)
                receiver = HashVoxelMap(MapParams(0.1), SensorModel(), d_inf=0.2)
                relay(share, receiver)
                a, b = sender.occupied_codes(), receiver.occupied_codes()
                row.update(sender_occupied=int(a.size), relayed_occupied=int(b.size),
                           relayed_holds=round(np.intersect1d(a, b).size / max(a.size, 1), 6))
            rows.append(row)
            print(json.dumps(row))
    Path(args.out).parent.mkdir(exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
