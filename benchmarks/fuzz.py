"""Mutation fuzzing of every voxtool decoder, outside the normal test run.

    python benchmarks/fuzz.py [--inputs 1000000] [--seed 0] [--out bench-results/fuzz.json]

Each input is a valid seed (PCD of all three DATA kinds, PLY, snapshot, packet of every scheme and codec,
packet log, OctoMap .bt) mutated by bit flips, byte overwrites with boundary values, truncation,
insertion and chunk duplication. A decoder may only return or raise VoxtoolError; anything else
is a crash (the input is saved under bench-results/fuzz_crashes/). An input taking over 5 s is a
hang. Peak RSS is reported: declared sizes are checked before allocation, so it stays bounded.
"""

from __future__ import annotations

import argparse
import io
import json
import resource
import struct
import sys
import tempfile
import time
import traceback
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def seeds() -> dict[str, list[bytes]]:
    from scenes import box_scene, lzf_literal

    from voxtool.codec.log import PacketLogWriter
    from voxtool.codec.packet import KIND_KEYFRAME, encode_packet, occupied_frame
    from voxtool.config import MapParams, SensorModel
    from voxtool.io.bt import bt_bytes
    from voxtool.io.snapshot import snapshot_bytes
    from voxtool.keys import morton_encode
    from voxtool.maps import make_backend
    from voxtool.maps.octree import OctreeMap
    from voxtool.sources.scan import Scan

    pts = box_scene(1, 30, seed=0)[0][0].astype("<f4")
    head = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 30\nHEIGHT 1\n"
            "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 30\nDATA {}\n")
    raw_cm = np.ascontiguousarray(pts.T).tobytes()
    comp = lzf_literal(raw_cm)
    pcd = [head.format("binary").encode() + pts.tobytes(),
           head.format("ascii").encode() + "".join(f"{a} {b} {c}\n" for a, b, c in pts.tolist()).encode(),
           head.format("binary_compressed").encode() + np.array([len(comp), len(raw_cm)], "<u4").tobytes() + comp]
    ply = [b"ply\nformat binary_little_endian 1.0\nelement vertex 30\nproperty float x\nproperty float y\n"
           b"property float z\nend_header\n" + pts.tobytes()]
    m = OctreeMap(MapParams(0.2), SensorModel())
    m.integrate(Scan(pts, np.zeros(3, np.float32)))
    snap = [snapshot_bytes({"backend": "octree", "map_params": m.params.to_dict(), "sensor_model": m.sensor.to_dict()},
                           m.state_arrays(), codec=c) for c in ("zstd", "raw")]
    # snapshots of the backends with their own state arrays, for the resealed target
    stateful = list(snap)
    for name, opts in (("hashmap", {"n_lim": 40, "d_inf": 0.4}), ("tiny", {"pool_blocks": 64, "map_size": 20.0})):
        b = make_backend(name, MapParams(0.2), SensorModel(), **opts)
        b.integrate(Scan(pts, np.zeros(3, np.float32)))
        header = {"backend": name, "map_params": b.params.to_dict(), "sensor_model": b.sensor.to_dict(),
                  "backend_params": b.extra_meta() if hasattr(b, "extra_meta") else {}}
        stateful.append(snapshot_bytes(header, b.state_arrays(), codec="raw"))
    keys = np.array([[5, 5, 5], [6, 7, 8], [9, 9, 9]])
    st = np.array([0, 1, 2], np.uint8)
    packets = [encode_packet("r", 1, 2, s, c, 0.1, keys, st, box=(np.array([4, 4, 4]), np.array([8, 8, 8])) if s == "racer" else None,
                             frames=[occupied_frame(1, morton_encode(keys))] if s == "occupied" else None)
               for s in ("hilbert", "nested", "racer", "occupied") for c in ("none", "zstd", "zlib")]
    packets.append(encode_packet("r", 0, 0, "hilbert", "zstd", 0.1, keys[:0], np.array([0, 1, 2, 0, 1, 1, 0, 2], np.uint8),
                                 kind=KIND_KEYFRAME, box=(np.array([1, 1, 1]), np.array([2, 2, 2]))))
    line = np.array([[20 + i, 20 + i // 2, 22] for i in range(12)])  # cm: a box with some structure
    packets.append(encode_packet("r", 3, 4, "nested", "cm", 0.1, line, np.array([0] * 11 + [1], np.uint8)))
    packets.append(encode_packet("r", 0, 0, "nested", "cm", 0.1, keys[:0], np.array([0, 1, 2, 0, 1, 1, 0, 2], np.uint8),
                                 kind=KIND_KEYFRAME, box=(np.array([1, 1, 1]), np.array([2, 2, 2]))))
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir) / "seed.mcap"
        with PacketLogWriter(tmp) as log:
            for i, p in enumerate(packets[:3]):
                log.write("r", i, 10 + i, p)
            log.metadata("r", {"first_stamp_ns": 0, "last_stamp_ns": 100})
        logs = [tmp.read_bytes()]
    bt = [bt_bytes(m.leaves(), 0.2, 0.0)]
    return {"pcd": pcd, "ply": ply, "snapshot": snap, "snapshot_resealed": stateful, "packet": packets,
            "packet_resealed": packets, "packet_log": logs, "bt": bt}


def targets():
    from voxtool.codec.fusion import fuse
    from voxtool.codec.log import read_log
    from voxtool.codec.packet import HEADER, decode_packet
    from voxtool.io.bt import parse_bt_bytes
    from voxtool.io.mapfile import backend_from_snapshot
    from voxtool.io.snapshot import parse_snapshot
    from voxtool.sources.pcd import parse_pcd
    from voxtool.sources.ply import parse_ply

    def log(blob):
        _, messages = read_log("fuzz.mcap", io.BytesIO(blob))
        for _robot, _, data in messages:
            decode_packet(data)

    def packet(blob):
        p = decode_packet(blob)
        fuse([], packets=iter([p]))

    def resealed(blob):
        """The mutated packet with its stored size and CRC made right again, so that mutations
        reach the size checks, the decompressors and the payload parsers behind the CRC."""
        if len(blob) >= HEADER.size:
            b = bytearray(blob)
            struct.pack_into("<I", b, 88, len(b) - HEADER.size)
            struct.pack_into("<I", b, 92, zlib.crc32(bytes(b[HEADER.size:]), zlib.crc32(bytes(b[: HEADER.size - 4]))))
            blob = bytes(b)
        packet(blob)  # decode_packet also reads an `occupied` packet's frames (what relay uses)

    def snapshot_resealed(blob):
        """The mutated snapshot with its array CRCs, header length and file CRC made right
        again, parsed and loaded into its backend (whose own checks then see the mutation)."""
        if len(blob) >= 20:
            (head_len,) = struct.unpack_from("<I", blob, 12)
            try:
                header = json.loads(blob[16 : 16 + head_len])
                payload = blob[16 + head_len : -4]
                for e in header["arrays"]:
                    off, n = int(e["offset"]), int(e["stored_bytes"])
                    e["crc32"] = zlib.crc32(payload[max(off, 0) : max(off, 0) + max(n, 0)])
                head = json.dumps(header).encode()
                body = blob[:12] + struct.pack("<I", len(head)) + head + payload
                blob = body + struct.pack("<I", zlib.crc32(body))
            except Exception:  # not resealable: the parser sees the bytes as they are
                pass
        backend_from_snapshot(parse_snapshot(blob), "fuzz.vxm")

    return {"pcd": parse_pcd, "ply": parse_ply, "snapshot": parse_snapshot, "snapshot_resealed": snapshot_resealed,
            "packet": packet, "packet_resealed": resealed, "packet_log": log, "bt": parse_bt_bytes}


BOUNDARY = [0x00, 0x01, 0x7F, 0x80, 0xFF]


def mutate(rng: np.random.Generator, blob: bytes) -> bytes:
    b = bytearray(blob)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(0, 6))
        if not b:
            b += bytes(rng.integers(0, 256, 4, dtype=np.uint8))
            continue
        i = int(rng.integers(0, len(b)))
        if op == 0:
            b[i] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            b[i] = BOUNDARY[int(rng.integers(0, len(BOUNDARY)))]
        elif op == 2:
            del b[i:]
        elif op == 3:
            b[i:i] = bytes(rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8))
        elif op == 4:
            j = min(len(b), i + int(rng.integers(1, 64)))
            b[i:i] = b[i:j]
        else:  # a length-like field set to something huge
            b[i : i + 4] = bytes([0xFF, 0xFF, 0xFF, 0x7F])
    return bytes(b)


def main() -> None:
    from voxtool.errors import VoxtoolError

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench-results/fuzz.json")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    pool, funcs = seeds(), targets()
    crash_dir = Path(args.out).parent / "fuzz_crashes"
    names = sorted(pool)
    per = {n: {"inputs": 0, "rejected": 0, "accepted": 0, "crashes": 0, "hangs": 0, "max_s": 0.0} for n in names}
    crashes = []
    t_start = time.time()
    for k in range(args.inputs):
        name = names[k % len(names)]
        seed_blob = pool[name][int(rng.integers(0, len(pool[name])))]
        blob = mutate(rng, seed_blob)
        row = per[name]
        row["inputs"] += 1
        t0 = time.perf_counter()
        try:
            funcs[name](blob)
            row["accepted"] += 1
        except VoxtoolError:
            row["rejected"] += 1
        except Exception as err:  # noqa: BLE001 - a crash is what we are looking for
            row["crashes"] += 1
            crash_dir.mkdir(parents=True, exist_ok=True)
            (crash_dir / f"{name}_{k}.bin").write_bytes(blob)
            crashes.append({"target": name, "input": k, "error": f"{type(err).__name__}: {err}",
                            "where": traceback.format_exc().strip().splitlines()[-3]})
        dt = time.perf_counter() - t0
        row["max_s"] = max(row["max_s"], dt)
        if dt > 5.0:
            row["hangs"] += 1
            crash_dir.mkdir(parents=True, exist_ok=True)
            (crash_dir / f"{name}_{k}_hang.bin").write_bytes(blob)
    elapsed = time.time() - t_start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    result = {"inputs": args.inputs, "seconds": round(elapsed, 1), "peak_rss_mib": round(peak, 1),
              "crashes": len(crashes), "hangs": sum(r["hangs"] for r in per.values()), "targets": per,
              "crash_samples": crashes[:20]}
    print(f"{'target':<11} {'inputs':>9} {'rejected':>9} {'accepted':>9} {'crashes':>8} {'hangs':>6} {'max ms':>8}")
    for n, r in per.items():
        print(f"{n:<11} {r['inputs']:>9} {r['rejected']:>9} {r['accepted']:>9} {r['crashes']:>8} {r['hangs']:>6} {1000 * r['max_s']:>8.1f}")
    print(f"total {args.inputs} inputs in {elapsed:.0f} s, {len(crashes)} crashes, peak RSS {peak:.0f} MiB")
    for c in crashes[:10]:
        print(c)
    Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
