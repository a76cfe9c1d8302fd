"""Replaying and fusing packet logs: every voxel takes the state of its latest-stamped observation.

Packets of all inputs are visited in (stamp, robot id, sequence) order (heapq.merge over inputs
that must each be in stamp order); a voxel's final state is the one set by the last packet
visited that mentions it. Keyframes set every cell of their box, unknown included.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from voxtool.codec.log import read_log
from voxtool.codec.packet import OCCUPIED, UNKNOWN, Packet, decode_packet
from voxtool.errors import FormatError, ParameterError
from voxtool.geometry import Pose
from voxtool.keys import coords_to_keys, keys_to_coords
from voxtool.sources.poses import UNIT_TOLERANCE


@dataclass
class Extrinsic:
    """Pose of a robot's map frame in the fused frame."""

    pose: Pose

    @classmethod
    def parse(cls, text: str) -> tuple[str, Extrinsic]:
        robot, _, rest = text.partition("=")
        try:
            v = [float(x) for x in rest.split(",")]
        except ValueError:
            v = []
        if not robot or len(v) != 7:
            raise ParameterError(f"--extrinsic '{text}' must read ROBOT=tx,ty,tz,qw,qx,qy,qz")
        if not np.all(np.isfinite(v)):
            raise ParameterError(f"--extrinsic '{text}' holds NaN or inf")
        norm = float(np.linalg.norm(v[3:]))
        if abs(norm - 1.0) > UNIT_TOLERANCE:  # as for pose files: a typo, not a rotation to normalise
            raise ParameterError(f"--extrinsic '{text}': quaternion has norm {norm:.6f}, expected a unit quaternion")
        return robot, cls(Pose.from_quat(v[:3], v[3], v[4], v[5], v[6]))

    def apply(self, keys: np.ndarray, resolution: float) -> np.ndarray:
        """Move keys into the fused frame: exact for grid-aligned translations, else the voxel
        centres are transformed and re-quantized (several voxels can land in one)."""
        shift = self.pose.translation / resolution
        if np.allclose(self.pose.rotation, np.eye(3), atol=1e-12) and np.allclose(shift, np.round(shift), atol=1e-9):
            moved = keys.astype(np.int64) + np.round(shift).astype(np.int64)
            if moved.size and (moved.min() < 0 or moved.max() > 65535):
                raise ParameterError("extrinsic moves voxels outside the key range")
            return moved.astype(np.uint16)
        centres = keys_to_coords(keys, resolution)
        return coords_to_keys(self.pose.apply(centres), resolution, what="transformed voxel")


@dataclass
class FusionResult:
    codes: np.ndarray  # sorted Morton codes of known voxels
    states: np.ndarray  # FREE / OCCUPIED (unknown dropped)
    resolution: float
    packets: int = 0
    robots: dict = field(default_factory=dict)  # robot -> {packets, gaps, first/last stamp}
    meta: dict = field(default_factory=dict)
    origin: tuple = (0.0, 0.0, 0.0)  # the packets' map_origin: where key 32768's corner sits in the scans' frame


class LatestStates:
    """Each voxel's latest state over packets added in order, kept as a sorted set and merged
    with batches of packets (a batch at least half the set: amortised linear). The set lives in
    buffers with room to grow, merged into in place, so memory is the set, its spare room and
    a batch, not every change of every packet.

    `background`: batches are sorted and merged on a thread of their own, one at a time and in
    order, while the caller goes on adding (and decoding) packets; memory is then at most two
    batches besides the set, and only the last batch's merge is left when the packets end."""

    MIN_BATCH = 1 << 20

    def __init__(self, background: bool = False) -> None:
        self._set_codes = np.zeros(0, np.int64)
        self._set_states = np.zeros(0, np.uint8)
        self.size = 0
        self._codes: list[np.ndarray] = []
        self._states: list[np.ndarray] = []
        self._pending = 0
        self._merger = None
        if background:
            from concurrent.futures import ThreadPoolExecutor

            self._merger = ThreadPoolExecutor(max_workers=1, thread_name_prefix="voxtool-fusion")
        self._merging = None  # the batch being merged on that thread

    def add(self, codes: np.ndarray, states: np.ndarray) -> None:
        self._codes.append(codes)
        self._states.append(states)
        self._pending += codes.shape[0]
        if self._pending >= max(self.MIN_BATCH, self.size // 2):
            self._merge()

    def _merge(self) -> None:
        if not self._codes:
            return
        batch = self._codes, self._states
        self._codes, self._states, self._pending = [], [], 0  # the packets' arrays go once the batch is joined
        if self._merger is None:
            self._merge_batch(*batch)
            return
        self._wait()  # one batch in flight: batches merge in the order they came
        self._merging = self._merger.submit(self._merge_batch, *batch)

    def _wait(self) -> None:
        if self._merging is not None:
            merging, self._merging = self._merging, None
            merging.result()  # raises what the merge raised

    def _merge_batch(self, codes: list, states: list) -> None:
        from voxtool.kernels.sort import latest_per_code, merge_latest_into

        joined = np.concatenate(codes), np.concatenate(states)
        codes.clear()  # the packets' arrays go now: the lists are still held by whoever called
        states.clear()
        codes, states = latest_per_code(*joined)
        del joined
        need = self.size + codes.shape[0]
        if need > self._set_codes.shape[0]:  # more room: an eighth more than is needed
            room = need + need // 8
            # grown in place: a large block is moved by remapping its pages (realloc's mremap), not
            # copied, so the old set and the new one are never both in memory (a copy was the peak
            # of merging a long log). Nothing else holds a view of these arrays while packets come.
            self._set_codes.resize(room, refcheck=False)
            self._set_states.resize(room, refcheck=False)
        self.size = merge_latest_into(self._set_codes, self._set_states, self.size, codes, states)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """The set (views of its buffers)."""
        try:
            self._merge()
            self._wait()
        finally:
            self.close()
        return self._set_codes[:self.size], self._set_states[:self.size]

    def close(self) -> None:
        """Stop the merging thread (after the batch it is merging); a no-op once stopped."""
        if self._merger is not None:
            self._merger.shutdown(wait=True)
            self._merger = None


def _log_packets(path: Path, extrinsics: dict | None = None):
    """(packet count, stream of ((stamp, robot, seq), path, (packet, its voxels' Morton codes in
    the fused frame))) of a log, checked in order; packets are decoded ahead on every core."""
    _, messages = read_log(path)
    extrinsics = extrinsics or {}

    def decode(message):
        robot, _, blob = message
        # a packet's voxels in any order: fusion sorts them by code itself
        p = decode_packet(blob, f"{path}: packet of '{robot}'", ordered=False)
        return p, _fused_codes(p, extrinsics)

    def stream():
        from voxtool.parallel import ordered_map, usable_cores

        last: dict[str, int] = {}
        # far enough ahead that the workers go on decoding while this thread merges a batch
        for p, codes in ordered_map(decode, messages, usable_cores(), ahead=64):
            if p.stamp_ns < last.get(p.robot, -1):
                raise FormatError(f"{path}: packet {p.seq} of robot '{p.robot}' (stamp {p.stamp_ns}) is older than the "
                                  "one before it")
            last[p.robot] = p.stamp_ns
            yield (p.stamp_ns, p.robot, p.seq), path, (p, codes)

    return messages.count, stream()


def fuse(paths: list[Path], extrinsics: dict[str, Extrinsic] | None = None, packets=None,
         progress: bool | None = False, on_packet=None) -> FusionResult:
    """Fuse logs (or given packets) by latest stamp; report sequence gaps per robot. `progress`:
    a bar over the packets on stderr (None: when stderr is a terminal). `on_packet(packet,
    codes)`: called for every packet fused, in fusion order, with its voxels' Morton codes in the
    fused frame (the replay of `--view`)."""
    from voxtool.kernels.sort import drop_state
    from voxtool.progress import track

    extrinsics = extrinsics or {}
    total = None
    if packets is None:
        paths = [Path(p) for p in paths]
        twice = sorted({str(p) for p in paths if paths.count(p) > 1})
        if twice:
            raise ParameterError(f"{twice[0]}: given twice (a log fused with itself would count its packets twice)")
        logs = [_log_packets(p, extrinsics) for p in paths]
        total = sum(count for count, _ in logs) if all(count is not None for count, _ in logs) else None
        ordered = heapq.merge(*(stream for _, stream in logs), key=lambda item: item[0])
        packets = ((path, p) for _, path, p in ordered)
    else:
        packets = ((None, (p, _fused_codes(p, extrinsics))) for p in packets)
    packets = track(packets, total, "fuse", progress, "packet")
    latest = LatestStates(background=True)
    robots: dict[str, dict] = {}
    resolution = first_from = origin = None
    rank = 0
    seen: dict[str, dict] = {}  # robot -> (seq, kind) -> the log it came from
    try:
        for path, (p, codes) in packets:
            where = f"{path}: " if path is not None else ""
            if resolution is None:
                resolution, first_from = p.resolution, path
            elif p.resolution != resolution:
                raise FormatError(f"{where}packet {p.seq} of robot '{p.robot}' has resolution {p.resolution} m, but "
                                  f"{first_from or 'the first packet'} has {resolution} m: fuse maps of one resolution")
            if origin is None:
                origin = tuple(p.map_origin)
            elif tuple(p.map_origin) != origin:
                raise FormatError(f"{where}packet {p.seq} of robot '{p.robot}' has map origin {list(p.map_origin)}, but "
                                  f"{first_from or 'the first packet'} has {list(origin)}: encode every robot's scans about "
                                  "one --origin X,Y,Z")
            info = robots.setdefault(p.robot, {"packets": 0, "first_stamp_ns": p.stamp_ns, "seqs": set()})
            seen_ids = seen.setdefault(p.robot, {})
            info["packets"] += 1
            info["last_stamp_ns"] = p.stamp_ns
            if (p.seq, p.kind) in seen_ids:
                other = seen_ids[(p.seq, p.kind)]
                if other != path:
                    raise ParameterError(f"{path}: packet {p.seq} of robot '{p.robot}' is also in {other}: the same robot's "
                                         "log given twice, or two robots' logs encoded under one name: encode each with "
                                         "its own --robot (the default is the log's file name)")
                continue  # duplicate delivery within one log
            seen_ids[(p.seq, p.kind)] = path
            if p.kind == 0:
                info["seqs"].add(p.seq)
            if on_packet is not None:
                on_packet(p, codes)
            latest.add(codes, p.states)
            rank += 1
    except BaseException:
        latest.close()  # its thread ends; what it merged is dropped with it
        raise
    codes, states = latest.result()
    _warn_clocks_apart(robots)
    for info in robots.values():
        seqs = sorted(info.pop("seqs"))
        missing = sorted(set(range(seqs[0], seqs[-1] + 1)) - set(seqs)) if seqs else []
        info["gaps"] = missing
    # a voxel last seen unknown is not in the fused map: dropped in place (a copy of the set was this command's peak)
    known = drop_state(codes, states, codes.shape[0], UNKNOWN)
    return FusionResult(codes[:known], states[:known], resolution or 0.0, rank, robots,
                        origin=origin or (0.0, 0.0, 0.0))


DAY_NS = 86_400 * 10**9


def _warn_clocks_apart(robots: dict[str, dict]) -> None:
    """Fusion by latest stamp means nothing between robots whose stamps are a day or more
    apart (one log stamped in epoch time, another from 0): say so."""
    import warnings

    from voxtool.errors import VoxtoolWarning

    if len(robots) < 2:
        return
    first = {robot: info["first_stamp_ns"] for robot, info in robots.items()}
    early, late = min(first, key=first.get), max(first, key=first.get)
    if first[late] - robots[early]["last_stamp_ns"] >= DAY_NS:
        days = (first[late] - first[early]) / DAY_NS
        warnings.warn(f"robot '{late}' is stamped {days:,.0f} days after robot '{early}': fusion by latest stamp lets "
                      f"'{late}' win every voxel both saw; fuse logs stamped on one clock", VoxtoolWarning, stacklevel=3)


def _fused_codes(p: Packet, extrinsics: dict) -> np.ndarray:
    """A packet's voxels as Morton codes in the fused frame (its robot's extrinsic applied)."""
    from voxtool.kernels.morton import key_codes

    keys = p.keys
    if p.robot in extrinsics:
        keys = extrinsics[p.robot].apply(keys, p.resolution)
    keys = np.ascontiguousarray(keys, dtype=np.uint16)  # one kernel type (keys are checked 0..65535)
    codes = np.empty(keys.shape[0], dtype=np.int64)
    key_codes(keys, codes)  # a pass in a compiled loop, not numpy's five over the array
    return codes


SAVE_PIECE = 1 << 20  # leaves a snapshot piece holds


def prune_in_parts(codes: np.ndarray, values: np.ndarray, depths: np.ndarray, threads: int) -> int:
    """kernels.sort.prune_into of sorted unique finest-level voxels, in place, in `threads` parts
    at once; returns how many leaves (the first ones of the arrays). The parts are split at
    multiples of a node span over an eighth of the voxels: a node across a split covers more
    voxels than there are, so it is never a leaf, and each part's leaves are the whole's."""
    from voxtool.kernels.sort import move_leaves, prune_into
    from voxtool.parallel import run_parts

    n = codes.shape[0]
    span = 1
    while 8 * span <= n:
        span *= 8
    cuts = sorted({0, n} | {int(np.searchsorted(codes, int(codes[n * k // threads]) // span * span))
                            for k in range(1, threads) if n})
    parts = [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]

    def prune(part):
        a, b = part
        return prune_into(codes[a:b], values[a:b], codes[a:b], depths[a:b], values[a:b])

    top = 0
    for (a, _), leaves in zip(parts, run_parts(threads, prune, parts)):
        if a > top:
            move_leaves(codes, depths, values, a, top, leaves)
        top += leaves
    return top


def save_state_map(path, result: FusionResult, info: dict) -> None:
    """Write the fused map as an octree snapshot. It consumes the result's voxels: they are
    pruned in place into the snapshot's leaves (the fused set is the largest thing in memory;
    a second copy was the command's peak), and the result is left without them."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.heap import give_back_freed_memory
    from voxtool.io.mapfile import save_map
    from voxtool.io.snapshot import ChunkedArrays
    from voxtool.maps.octree import OctreeMap
    from voxtool.parallel import usable_cores

    sensor = SensorModel()
    m = OctreeMap(MapParams(resolution=result.resolution or 0.1), sensor)  # its parameters; the leaves are below
    codes, states = np.ascontiguousarray(result.codes), np.ascontiguousarray(result.states)
    result.codes = result.states = None
    give_back_freed_memory()  # fusion's freed batches, before the save adds its own memory
    depths = np.empty(codes.shape[0], np.uint8)
    # the octree's pruned leaves, straight from the sorted voxels (pruned by state: each state is
    # one log-odds value) and no tree built to be saved; the log-odds made for the leaves alone
    top = prune_in_parts(codes, states, depths, usable_cores())
    codes, depths, states = codes[:top], depths[:top], states[:top]
    occupied, free = np.float32(sensor.clamp_max_log), np.float32(sensor.clamp_min_log)

    def pieces():
        # the snapshot's bytes are those of the whole table; written a piece at a time, its
        # encoding holds a piece's planes and log-odds, not the table's (100 MB on kaist03)
        for at in range(0, top, SAVE_PIECE):
            end = min(at + SAVE_PIECE, top)
            yield codes[at:end], depths[at:end], np.where(states[at:end] == OCCUPIED, occupied, free)

    table = ChunkedArrays(("leaf_codes", "leaf_depths", "leaf_values"), ("int64", "uint8", "float32"), top, pieces)
    save_map(path, m, {**info, "origin": [float(v) for v in result.origin]}, dict.fromkeys(table.names, table))


def packets_of(path: Path) -> list[Packet]:
    return [p for _, _, (p, _) in _log_packets(path)[1]]
