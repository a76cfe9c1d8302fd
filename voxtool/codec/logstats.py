"""Bandwidth statistics of packet logs (`voxtool stats LOG.mcap`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.codec.log import PacketHeader, read_log
from voxtool.codec.packet import HEADER, decode_packet


def log_stats(path: str | Path, progress: bool | None = False, series: dict | None = None) -> dict:
    """Packets, bytes, average and 1-second-window maximum bandwidth per robot and in total,
    compression ratio, bytes per changed voxel, and the ratio to the raw sensor bandwidth.
    `series` (a dict) receives robot -> (packet stamps in ns, packet bytes), for `stats --plot`."""
    from voxtool.progress import track

    path = Path(path)
    meta, messages = read_log(path, headers=True)
    rows: dict[str, dict] = {}
    stamps, sizes = [], []
    for h in track(messages, messages.count, "stats", progress, "packet"):
        r = rows.get(h.robot)
        if r is None:
            r = rows[h.robot] = {"packets": 0, "keyframes": 0, "bytes": 0, "raw_payload_bytes": 0,
                                 "stored_payload_bytes": 0, "changed_voxels": 0, "racer_bytes": 0, "stamps": [],
                                 "sizes": [], "scheme": h.scheme, "codec": h.codec}
        size = h.wire_bytes
        r["packets"] += 1
        r["bytes"] += size
        r["raw_payload_bytes"] += h.raw_size
        r["stored_payload_bytes"] += h.stored_size
        if h.kind == 0:
            # a delta's header counts the voxels it changes, except an `occupied` packet's (frames)
            changed = h.count if h.scheme != "occupied" else _occupied_voxels(h, path)
            r["changed_voxels"] += changed
            r["racer_bytes"] += HEADER.size + racer_payload_bytes(changed, h.box_cells)
        else:
            r["keyframes"] += 1
        r["stamps"].append(h.stamp_ns)
        r["sizes"].append(size)
        stamps.append(h.stamp_ns)
        sizes.append(size)
    out_robots = {}
    for robot, r in rows.items():
        m = meta.get(robot, {})
        span = _span(m, r["stamps"])
        robot_stamps, robot_sizes = np.array(r.pop("stamps"), np.int64), np.array(r.pop("sizes"), np.int64)
        if series is not None:
            series[robot] = (robot_stamps, robot_sizes)
        bw = _bandwidth(robot_stamps, robot_sizes, span)
        raw_bps = m.get("raw_sensor_bytes", 0) / span if span else None
        r.update(bw)
        r["duration_s"] = round(span, 6)
        # each ratio named by what it is against (docs/packets.md)
        r["compression_ratio"] = round(r["raw_payload_bytes"] / max(r["stored_payload_bytes"], 1), 3)
        r["vs_racer"] = round(r.pop("racer_bytes") / max(r["bytes"], 1), 3) if r["changed_voxels"] else None
        r["bytes_per_changed_voxel"] = round(r["bytes"] / max(r["changed_voxels"], 1), 4)
        r["raw_sensor_Bps"] = round(raw_bps, 1) if raw_bps else None
        r["ratio_to_raw_sensor"] = round(r["avg_Bps"] / raw_bps, 6) if raw_bps else None
        out_robots[robot] = r
    total_span = max((_span(meta.get(k, {}), []) for k in rows), default=0.0) or 1.0
    total = _bandwidth(np.array(stamps), np.array(sizes), total_span) if stamps else {"avg_Bps": 0, "max_Bps": 0}
    return {"log": str(path), "packets": len(sizes), "bytes": int(sum(sizes)), "header_bytes": HEADER.size,
            "total": total, "robots": out_robots}


def _span(meta: dict, stamps: list[int]) -> float:
    if "first_stamp_ns" in meta and "last_stamp_ns" in meta:
        return max(meta["last_stamp_ns"] - meta["first_stamp_ns"], 1) / 1e9
    return max((max(stamps) - min(stamps)) / 1e9, 1.0) if stamps else 1.0


def _bandwidth(stamps: np.ndarray, sizes: np.ndarray, span: float) -> dict:
    """Average over the log's span; maximum over 1 s windows aligned to the first packet."""
    if stamps.size == 0:
        return {"avg_Bps": 0.0, "max_Bps": 0.0}
    bins = ((stamps - stamps.min()) // 1_000_000_000).astype(np.int64)
    # only the windows that hold packets: robots on clocks years apart would make billions
    _, window = np.unique(bins, return_inverse=True)
    per_second = np.bincount(window.ravel(), weights=sizes)
    avg = float(sizes.sum()) / span
    # a log shorter than one window (or ending in a partial one) would report a maximum below
    # its own average; the busiest second is never quieter than the average
    return {"avg_Bps": round(avg, 1), "max_Bps": round(max(float(per_second.max()), avg), 1)}


def racer_payload_bytes(changed: int, cells: int) -> int:
    """RACER's payload for `changed` voxels of a box of `cells`: an address of the fewest whole
    bytes that index the box, and a 2-bit state, per voxel (the paper's Fig. 5 rule); addressed in
    the packet's own box, the least RACER could spend (it addresses the whole map)."""
    width = max(1, (max(cells - 1, 1).bit_length() + 7) // 8)  # address_width's rule, on one int (per packet)
    return changed * width + (changed + 3) // 4


def _occupied_voxels(h: PacketHeader, path: Path) -> int:
    """Voxels an `occupied` packet sets (its header counts frames): the packet is decoded."""
    return int(decode_packet(h.packet(), f"{path}: packet of '{h.robot}'").keys.shape[0])
