"""Request/response resend over a lossy loopback channel (seed ogm-sync-hilbert.md, Sec. IV-B).

Robots (responders) publish their packets at their stamps to one receiver (the fusion side)
over a channel that loses, delays (so reorders) and duplicates messages. Every `request_period`
seconds the receiver publishes, per robot, the index intervals it holds. A responder answers with
the packets the requester lacks, but only those that were already missing in the previous request
and were not sent within the channel's maximum delay (they may merely be delayed), under a byte
budget per second; when more than `keyframe_gap` are missing it sends one full-state keyframe of
its current map instead. The simulation ends when the receiver holds every robot's packets.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxtool.codec.fusion import Extrinsic, fuse
from voxtool.codec.packet import decode_packet, keyframe_packet
from voxtool.errors import ParameterError


@dataclass
class ChannelModel:
    loss: float = 0.3
    max_delay: float = 0.3  # seconds; uniform delay makes later packets overtake earlier ones
    duplicate: float = 0.1
    request_period: float = 0.5
    rate_limit_Bps: float = 5e6
    keyframe_gap: int = 1000
    max_rounds: int = 10_000

    def __post_init__(self) -> None:
        # written so that NaN fails every check
        if not 0 <= self.loss < 1:
            raise ParameterError(f"loss rate {self.loss} (--simulate-loss) must lie in [0, 1)")
        if not 0 <= self.duplicate < 1:
            raise ParameterError(f"duplicate rate {self.duplicate} must lie in [0, 1)")
        if not (0 <= self.max_delay < math.inf and 0 < self.request_period < math.inf and self.rate_limit_Bps > 0):
            raise ParameterError("channel delay, request period and rate limit must be finite and positive")


def intervals(held: set[int]) -> list[tuple[int, int]]:
    """Sorted, disjoint [a, b] runs covering `held` (what a request carries)."""
    runs: list[tuple[int, int]] = []
    for i in sorted(held):
        if runs and i == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], i)
        else:
            runs.append((i, i))
    return runs


def missing_from(runs: list[tuple[int, int]], upto: int) -> list[int]:
    have = np.zeros(upto + 1, dtype=bool)
    for a, b in runs:
        have[a : min(b, upto) + 1] = True
    return [int(i) for i in np.flatnonzero(~have)]


def _keyframe(robot: str, packets: list, upto: int) -> bytes:
    """Full-state keyframe of a robot's own map after its packets 0..upto."""
    own = fuse([], packets=iter(packets[: upto + 1]))
    last = packets[upto]
    # in the robot's own box coding when it has one (cm keyframes are smaller), else hilbert/zstd
    scheme, codec = (last.scheme, last.codec) if last.scheme in ("hilbert", "nested") else ("hilbert", "zstd")
    return keyframe_packet(robot, upto, last.stamp_ns, scheme, codec, last.resolution, own.codes, own.states)


def simulate(paths: list[Path], loss: float = 0.3, seed: int = 0, extrinsics: dict[str, Extrinsic] | None = None,
             channel: ChannelModel | None = None, blobs: dict[str, list[bytes]] | None = None) -> dict:
    """Run the simulation; compare the receiver's fused map with the lossless fusion."""
    ch = channel or ChannelModel(loss=loss)
    rng = np.random.default_rng(seed)
    if blobs is None:
        from voxtool.codec.log import read_log

        blobs = {}
        for path in paths:
            _, messages = read_log(path)
            for robot, _, blob in messages:
                blobs.setdefault(robot, []).append(blob)
    own = {r: [decode_packet(b) for b in bl] for r, bl in blobs.items()}
    for r, packets in own.items():
        order = sorted(range(len(packets)), key=lambda i: packets[i].seq)
        own[r] = [packets[i] for i in order]
        blobs[r] = [blobs[r][i] for i in order]
        if [p.seq for p in own[r]] != list(range(len(packets))):
            raise ValueError(f"robot {r}: the simulation needs complete logs (sequence 0..n-1)")
    t0 = min(p.stamp_ns for ps in own.values() for p in ps)
    events: list = []  # (time s, order, kind, robot, payload)
    counter = 0
    stats = {"sent": 0, "lost": 0, "duplicates": 0, "resent": 0, "keyframes": 0, "bytes_sent": 0,
             "bytes_resent": 0, "requests": 0, "rounds": 0}

    def transmit(t: float, robot: str, payload, nbytes: int, resend: bool) -> None:
        nonlocal counter
        stats["sent"] += 1
        stats["bytes_sent"] += nbytes
        if resend:
            stats["resent"] += 1
            stats["bytes_resent"] += nbytes
        if rng.random() < ch.loss:
            stats["lost"] += 1
            return
        copies = 2 if rng.random() < ch.duplicate else 1
        stats["duplicates"] += copies - 1
        for _ in range(copies):
            counter += 1
            heapq.heappush(events, (t + rng.uniform(0, ch.max_delay), counter, "packet", robot, payload))

    for robot, packets in own.items():
        for i, p in enumerate(packets):
            transmit((p.stamp_ns - t0) / 1e9, robot, ("delta", i), len(blobs[robot][i]), False)
    end_of_stream = max((p.stamp_ns - t0) / 1e9 for ps in own.values() for p in ps)
    held = {r: set() for r in own}
    covered_by_keyframe = {r: -1 for r in own}
    received: dict[str, dict[int, object]] = {r: {} for r in own}
    previous_missing = {r: set() for r in own}
    last_sent = {r: {} for r in own}
    t = 0.0
    while stats["rounds"] < ch.max_rounds:
        t += ch.request_period
        while events and events[0][0] <= t:
            _, _, _, robot, (kind, payload) = heapq.heappop(events)
            if kind == "delta":
                held[robot].add(payload)
                received[robot][payload] = own[robot][payload]
            else:
                upto, blob = payload
                held[robot].update(range(upto + 1))
                covered_by_keyframe[robot] = max(covered_by_keyframe[robot], upto)
                received[robot][("kf", upto)] = decode_packet(blob)
        if t >= end_of_stream and all(len(held[r]) == len(own[r]) for r in own) and not events:
            break
        stats["rounds"] += 1
        for robot, packets in own.items():
            upto = max((i for i, p in enumerate(packets) if (p.stamp_ns - t0) / 1e9 <= t), default=-1)
            if upto < 0:
                continue
            stats["requests"] += 1
            if rng.random() < ch.loss:  # the request itself can be lost
                continue
            missing = missing_from(intervals(held[robot]), upto)
            due = [i for i in missing if i in previous_missing[robot]
                   and t - last_sent[robot].get(i, -1e9) > ch.max_delay]
            previous_missing[robot] = set(missing)
            if len(due) > ch.keyframe_gap:
                kf = _keyframe(robot, packets, upto)
                stats["keyframes"] += 1
                transmit(t, robot, ("keyframe", (upto, kf)), len(kf), True)
                continue
            budget = ch.rate_limit_Bps * ch.request_period
            for i in due:
                size = len(blobs[robot][i])
                if size > budget:
                    break
                budget -= size
                last_sent[robot][i] = t
                transmit(t, robot, ("delta", i), size, True)
    got = [p for r in received for p in received[r].values()]
    got.sort(key=lambda p: (p.stamp_ns, p.robot, p.seq, p.kind))
    fused = fuse([], extrinsics, packets=iter(got))
    lossless = fuse([], extrinsics, packets=iter(sorted((p for ps in own.values() for p in ps),
                                                        key=lambda p: (p.stamp_ns, p.robot, p.seq))))
    stats["complete"] = all(len(held[r]) == len(own[r]) for r in own)
    stats["equal_to_lossless"] = bool(np.array_equal(fused.codes, lossless.codes)
                                      and np.array_equal(fused.states, lossless.states))
    stats["sim_seconds"] = round(t, 3)
    return stats


