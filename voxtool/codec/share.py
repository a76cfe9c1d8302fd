"""Map sharing of the hash-map backend (seed voxel-mapping-hash-map-sharing.md, Sec. V-C).

After each scan the voxels that became occupied form a frame; a ring buffer keeps the last k
frames and every broadcast carries the whole ring, so a receiver that missed broadcasts catches
up. Broadcasts are `occupied`-scheme packets (formats/packet.md) in an MCAP packet log. A
receiver integrates each frame once (deduplicated by frame sequence) like sensor hits, without
ray casting.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np

from voxtool.codec.log import PacketLogWriter, read_log
from voxtool.codec.packet import decode_packet, encode_packet, occupied_frame
from voxtool.errors import ParameterError


class ShareWriter:
    """Pipeline hook: after each scan, broadcast the ring of the last k newly-occupied frames."""

    def __init__(self, path: str | Path, robot: str, ring: int, codec: str, resolution: float) -> None:
        if ring < 1:
            raise ParameterError(f"--ring {ring}: a broadcast carries at least the last frame (k >= 1)")
        self.log = PacketLogWriter(path)
        self.robot, self.codec, self.resolution = robot, codec, resolution
        self.ring: deque = deque(maxlen=ring)
        self.seq = 0
        self.bytes = 0
        self.raw_sensor_bytes = 0
        self.first = self.last = None

    def __call__(self, scan, backend) -> None:
        stamp = scan.stamp_ns if scan.stamp_ns else scan.index * 100_000_000
        self.ring.append(occupied_frame(scan.index, backend.newly_occupied))  # encoded once, sent k times
        blob = encode_packet(self.robot, self.seq, stamp, "occupied", self.codec, self.resolution,
                             np.zeros((0, 3)), np.zeros(0, np.uint8), frames=list(self.ring))
        self.log.write(self.robot, self.seq, stamp, blob)
        self.seq += 1
        self.bytes += len(blob)
        self.raw_sensor_bytes += scan.raw_bytes
        self.first = stamp if self.first is None else self.first
        self.last = stamp

    def close(self, ok: bool, period_ns: int = 100_000_000) -> None:
        if ok:
            self.log.metadata(self.robot, {"robot": self.robot, "scheme": "occupied", "codec": self.codec,
                                           "resolution": self.resolution, "raw_sensor_bytes": self.raw_sensor_bytes,
                                           "first_stamp_ns": self.first or 0, "last_stamp_ns": (self.last or 0) + period_ns})
        self.log.close(ok)


def relay(log: str | Path, backend) -> int:
    """Integrate the shared frames of a log into `backend` (a hash map); returns frames used."""
    _, messages = read_log(log)
    seen: set[tuple[str, int]] = set()
    used = 0
    for robot, _, blob in messages:
        p = decode_packet(blob, f"{log}: packet of '{robot}'")
        if p.scheme != "occupied":
            continue
        for fseq, keys in p.frames:
            if (p.robot, fseq) in seen:
                continue
            seen.add((p.robot, fseq))
            backend.integrate_shared(keys, p.stamp_ns, fseq)
            used += 1
    return used
