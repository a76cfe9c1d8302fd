"""`voxtool encode`: run a map over a scan stream and emit map-change packets (seed Alg. 1)."""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from voxtool.codec.log import PacketLogWriter
from voxtool.codec.packet import FREE, OCCUPIED, UNKNOWN, encode_packet, keyframe_packet, occupied_frame
from voxtool.errors import ParameterError
from voxtool.kernels.morton import code_keys
from voxtool.keys import key_bounds, morton_decode
from voxtool.maps.base import MapBackend, removed_voxels, update_codes
from voxtool.parallel import one_blas_thread, resolve_threads, run_parts
from voxtool.sources import ScanStream
from voxtool.sources.scan import add_drop_counts


def robot_from_path(path) -> str:
    """A robot id from a log's file name (its stem, cut to the format's 16 bytes at a character)."""
    from pathlib import Path

    name = Path(path).stem or "r1"
    while len(name.encode()) > 16:
        name = name[:-1]
    return name


@dataclass(frozen=True)
class EncodeOptions:
    robot: str | None = "r1"  # None: named after the log's file (robot_from_path)
    scheme: str = "hilbert"
    codec: str = "zstd"
    max_changes: int = 50_000  # d: emit when this many voxels changed state
    max_interval: float = 0.5  # t: or when this much scan time passed since the last packet (s)
    ring: int = 3  # k frames per `occupied` packet
    keyframe_every: int = 0  # also emit a full-state keyframe every n packets (0: never)
    rate_hz: float = 10.0  # scan rate assumed when the source carries no stamps
    # the scans' position of the map's key-32768 corner: the local origin of a map built with --origin
    map_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        # written so that NaN fails too; an infinite interval (packets by count only) is allowed
        if not (self.max_changes >= 1 and self.max_interval > 0 and self.ring >= 1 and 0 < self.rate_hz < math.inf):
            raise ParameterError("--max-changes, --max-interval, --ring and --rate must be positive")
        if self.keyframe_every < 0:
            raise ParameterError(f"--keyframe-every {self.keyframe_every} must be >= 0 (0: no keyframes)")
        if self.codec in ("cm", "cm1") and self.scheme != "nested":
            raise ParameterError(f"--codec cm codes boxes in x-y-z order: use it with --scheme nested, not {self.scheme}")
        if self.robot is not None and (not self.robot or len(self.robot.encode()) > 16):
            raise ParameterError(f"robot id '{self.robot}' must be 1..16 bytes")


def voxel_states(values: np.ndarray, threshold_log: float) -> np.ndarray:
    """FREE / OCCUPIED / UNKNOWN of log-odds (NaN = unknown), by the map's threshold."""
    out = np.where(values > np.float32(threshold_log), OCCUPIED, FREE).astype(np.uint8)
    out[np.isnan(values)] = UNKNOWN
    return out


MAX_PLANE = 1 << 24  # cells in one z-plane of a box (a cm coder keeps three planes of classes)


def split_changes(codes: np.ndarray, max_count: int, density: int = 256,
                  keys: np.ndarray | None = None) -> list[tuple[int, int]]:
    """Split Morton-sorted changed voxels into runs of at most `max_count` whose bounding box
    holds at most max(density * count, 2^18) cells (density 0: no volume limit, but at most
    2^30 cells and MAX_PLANE cells a plane), cutting at octree node boundaries. `keys`: the
    codes' keys (morton_decode), when the caller has them.

    Our choice (formats/packet.md): one box over a long-range LiDAR scan's changes spans the
    whole sensor range and is mostly 'unchanged' cells; octree-aligned runs keep boxes compact."""
    out: list[tuple[int, int]] = []
    if keys is None:
        keys = morton_decode(codes)
    stack = [(0, codes.shape[0])]
    while stack:
        a, b = stack.pop()
        n = b - a
        if n == 0:
            continue
        if n <= max_count:
            if n == 1:
                out.append((a, b))
                continue
            lo, hi = key_bounds(keys[a:b])
            dims = hi - lo + 1
            cells = int(np.prod(dims))
            fits = cells <= 1 << 30 and int(dims[0] * dims[1]) <= MAX_PLANE if density <= 0 else \
                cells <= max(density * n, 1 << 18)
            if fits:
                out.append((a, b))
                continue
        # cut where the highest differing Morton bit of the run's ends flips
        top = int(codes[a] ^ codes[b - 1]).bit_length() - 1
        prefix = (int(codes[b - 1]) >> top) << top
        mid = int(np.searchsorted(codes[a:b], prefix)) + a
        if mid <= a or mid >= b:
            mid = a + n // 2
        stack.append((mid, b))
        stack.append((a, mid))
    return out


def merge_latest(codes_a, states_a, codes_b, states_b):
    """Union of two change sets keeping b's state where both hold a voxel (sorted unique codes):
    the latest state per code of a then b, as fusion keeps it (kernels.sort.latest_per_code)."""
    from voxtool.kernels.sort import latest_per_code

    return latest_per_code(np.concatenate([codes_a, codes_b]), np.concatenate([states_a, states_b]))


@dataclass
class EncodeReport:
    scans: int = 0
    packets: int = 0
    keyframes: int = 0
    wire_bytes: int = 0
    changed_voxels: int = 0
    raw_sensor_bytes: int = 0
    first_stamp_ns: int = 0
    last_stamp_ns: int = 0
    time_map_s: float = 0.0
    time_encode_s: float = 0.0
    encoded_cells: int = 0
    dropped: dict = field(default_factory=dict)  # points dropped on reading, by reason (Scan.drop_counts)

    def to_dict(self) -> dict:
        span = max(self.last_stamp_ns - self.first_stamp_ns, 1) / 1e9
        return {
            "scans": self.scans, "packets": self.packets, "keyframes": self.keyframes, "bytes": self.wire_bytes,
            "changed_voxels": self.changed_voxels, "raw_sensor_bytes": self.raw_sensor_bytes,
            "duration_s": round(span, 6), "avg_bandwidth_Bps": round(self.wire_bytes / span, 1),
            "raw_sensor_Bps": round(self.raw_sensor_bytes / span, 1),
            "bytes_per_changed_voxel": round(self.wire_bytes / max(self.changed_voxels, 1), 4),
            "time_map_s": round(self.time_map_s, 4), "time_encode_s": round(self.time_encode_s, 4),
            "encode_cells_per_s": round(self.encoded_cells / max(self.time_encode_s, 1e-9)),
            **self.dropped,
        }


def encode_stream(stream: ScanStream, backend: MapBackend, output, opts: EncodeOptions, info: dict,
                  progress: bool | None = None) -> dict:
    """Map every scan, accumulate state changes, write packets to an MCAP log at `output`."""
    from tqdm import tqdm

    if progress is None:
        progress = sys.stderr.isatty()
    thr = backend.sensor.threshold_log
    res = backend.params.resolution
    rep = EncodeReport()
    pend_codes = np.zeros(0, np.int64)
    pend_states = np.zeros(0, np.uint8)
    frames: deque = deque(maxlen=opts.ring)  # the ring of `occupied` frames, each encoded once
    map_lo = np.full(3, 65535, np.int64)
    map_hi = np.zeros(3, np.int64)
    seq = 0
    last_emit = None
    period = int(1e9 / opts.rate_hz)
    threads = resolve_threads(getattr(backend, "threads", 0))
    backend.warm_up()
    if opts.codec in ("cm", "cm1"):
        from voxtool.codec.cm import warm_up

        warm_up(opts.codec, decode=False)

    with PacketLogWriter(output) as log:

        def emit(stamp: int) -> None:
            nonlocal seq, pend_codes, pend_states
            # the keys once (one compiled pass): the split and every packet take slices of them
            pend_keys = np.empty((pend_codes.shape[0], 3), np.uint16)
            code_keys(pend_codes, pend_keys)
            if opts.scheme in ("hilbert", "nested"):
                # cm spends next to nothing on empty cells (docs/packets.md): boxes split by count only
                runs = split_changes(pend_codes, opts.max_changes, density=0 if opts.codec in ("cm", "cm1") else 256,
                                     keys=pend_keys)
            elif opts.scheme == "racer":
                runs = [(a, min(a + opts.max_changes, pend_codes.shape[0]))
                        for a in range(0, max(pend_codes.shape[0], 1), opts.max_changes)]
            else:
                runs = [(0, pend_codes.shape[0])]
            def packet(job: tuple[int, tuple[int, int]]) -> tuple[bytes, int]:
                k, (a, b) = job
                keys = pend_keys[a:b]
                box, cells = None, 0
                if opts.scheme == "racer":
                    box = (map_lo, map_hi - map_lo + 1)
                elif opts.scheme in ("hilbert", "nested") and keys.shape[0]:
                    lo, hi = key_bounds(keys)
                    box = (lo, hi - lo + 1)
                    cells = int(np.prod(box[1]))
                return encode_packet(opts.robot, seq + k, stamp, opts.scheme, opts.codec, res, keys, pend_states[a:b],
                                     box=box, map_origin=opts.map_origin,
                                     frames=list(frames) if opts.scheme == "occupied" else None), cells

            t0 = time.perf_counter()
            # the packets of one emission are built side by side (numba's kernels and zstd release
            # the GIL; each packet is coded on its own, so the bytes are those of one thread)
            built = run_parts(threads, packet, list(enumerate(runs)))
            rep.time_encode_s += time.perf_counter() - t0
            for blob, cells in built:
                rep.encoded_cells += cells
                log.write(opts.robot, seq, stamp, blob)
                rep.packets += 1
                rep.wire_bytes += len(blob)
                seq += 1
            rep.changed_voxels += int(pend_codes.shape[0])
            pend_codes, pend_states = pend_codes[:0], pend_states[:0]
            if opts.keyframe_every and seq % opts.keyframe_every == 0 and opts.scheme in ("hilbert", "nested"):
                kf = keyframe_blob(backend, opts, seq, stamp)
                log.write(opts.robot, seq, stamp, kf)
                rep.keyframes += 1
                rep.wire_bytes += len(kf)
                seq += 1

        bar = tqdm(total=stream.count, unit="scan", disable=not progress, file=sys.stderr, desc="encode")
        blas = one_blas_thread()
        try:
            for scan in stream.scans:
                stamp = scan.stamp_ns if scan.stamp_ns else scan.index * period
                if rep.scans == 0:
                    rep.first_stamp_ns = stamp
                t0 = time.perf_counter()
                prepared = backend.prepare(scan)
                codes = update_codes(backend, prepared)
                before = voxel_states(backend.query(codes), thr)
                backend.apply(prepared)
                after = voxel_states(backend.query(codes), thr)
                gone = removed_voxels(backend)
                if gone is not None and gone[0].shape[0]:
                    # voxels the map dropped that the scan did not update (voxel limit, TTL)
                    extra = ~np.isin(gone[0], codes)
                    codes = np.concatenate([codes, gone[0][extra]])
                    before = np.concatenate([before, voxel_states(gone[1][extra], thr)])
                    after = np.concatenate([after, voxel_states(backend.query(gone[0][extra]), thr)])
                    order = np.argsort(codes)
                    codes, before, after = codes[order], before[order], after[order]
                rep.time_map_s += time.perf_counter() - t0
                changed = before != after
                if opts.scheme == "racer" and changed.any():  # the box of every voxel that ever changed: RACER's addresses
                    ck_lo, ck_hi = key_bounds(morton_decode(codes[changed]))
                    map_lo = np.minimum(map_lo, ck_lo)
                    map_hi = np.maximum(map_hi, ck_hi)
                new_occ = codes[changed & (after == OCCUPIED)]
                if opts.scheme == "occupied":
                    frames.append(occupied_frame(rep.scans, new_occ))
                pend_codes, pend_states = merge_latest(pend_codes, pend_states, codes[changed], after[changed])
                rep.scans += 1
                rep.raw_sensor_bytes += scan.raw_bytes
                add_drop_counts(rep.dropped, scan)
                rep.last_stamp_ns = stamp
                if last_emit is None:
                    last_emit = stamp
                due = (pend_codes.shape[0] >= opts.max_changes or stamp - last_emit >= opts.max_interval * 1e9
                       or opts.scheme == "occupied")
                if due:
                    emit(stamp)
                    last_emit = stamp
                bar.update(1)
            if pend_codes.shape[0]:
                emit(rep.last_stamp_ns)
        finally:
            blas.restore_original_limits()
            bar.close()
        # the data covers one scan period past the last scan's stamp
        rep.last_stamp_ns += period if rep.scans else 0
        meta = {**info, "robot": opts.robot, "scheme": opts.scheme, "codec": opts.codec,
                "max_changes": opts.max_changes, "max_interval": opts.max_interval, "ring": opts.ring,
                "resolution": res, "raw_sensor_bytes": rep.raw_sensor_bytes, "scans": rep.scans,
                "first_stamp_ns": rep.first_stamp_ns, "last_stamp_ns": rep.last_stamp_ns}
        log.metadata(opts.robot, meta)
    out = rep.to_dict()
    out.update(robot=opts.robot, scheme=opts.scheme, codec=opts.codec, output=str(output))
    return out


def keyframe_blob(backend: MapBackend, opts: EncodeOptions, seq: int, stamp: int) -> bytes:
    """Full-state keyframe (free / occupied / unknown, no 'unchanged') of the map's known box."""
    from voxtool.keys import expand_leaves

    lv = backend.leaves()
    codes = expand_leaves(lv.codes, lv.depths)
    values = np.repeat(lv.values, np.left_shift(1, 3 * (16 - lv.depths.astype(np.int64))))
    return keyframe_packet(opts.robot, seq, stamp, opts.scheme, opts.codec, backend.params.resolution, codes,
                           voxel_states(values, backend.sensor.threshold_log), opts.map_origin)
