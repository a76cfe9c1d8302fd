"""Regenerate formats/vectors: small snapshots (.vxm) and their JSON description."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from voxtool.io.snapshot import snapshot_bytes

OUT = Path(__file__).resolve().parents[1] / "formats" / "vectors"


def describe(header: dict, arrays: dict) -> dict:
    return {"header": header, "arrays": {k: {"dtype": v.dtype.name, "shape": list(v.shape), "values": v.ravel().tolist()}
                                         for k, v in arrays.items()}}


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    base = {"voxtool_version": "0.1.0", "backend": "octree",
            "map_params": {"resolution": 0.2, "max_range": -1.0, "min_range": 0.0},
            "sensor_model": {"prob_hit": 0.7, "prob_miss": 0.4, "clamp_min": 0.1192, "clamp_max": 0.971,
                             "occupancy_threshold": 0.5},
            "backend_params": {}, "info": {"source": "golden", "scans": 1, "points": 2, "points_dropped": 0}}
    cases = {
        "snapshot_empty": {"leaf_codes": np.zeros(0, np.int64), "leaf_depths": np.zeros(0, np.uint8),
                           "leaf_values": np.zeros(0, np.float32)},
        # key (32768, 32768, 32768) = voxel [0, 0.2)^3 has Morton code 7 << 45 = 0xE00000000000; its +x
        # neighbour is code + 1; the depth-15 leaf covers the 2x2x2 voxels from code + 8
        "snapshot_three_leaves": {
            "leaf_codes": np.array([0xE00000000000, 0xE00000000001, 0xE00000000008], np.int64),
            "leaf_depths": np.array([16, 16, 15], np.uint8),
            "leaf_values": np.array([-0.4054651, 0.8472979, -1.9924302], np.float32)},
    }
    # the delta8 layout of leaf codes (formats/snapshot.md): differences from the code before, as
    # 8 byte planes; a zstd snapshot stores its leaf codes so, compressed
    planed = {"snapshot_delta8": {
        "leaf_codes": np.array([0xE00000000000, 0xE00000000001, 0xE00000000008, 0xE00000000040,
                                0xF00000000000], np.int64),
        "leaf_depths": np.array([16, 16, 15, 14, 1], np.uint8),
        "leaf_values": np.array([-0.4054651, 0.8472979, -1.9924302, 3.5, -2.0], np.float32)}}
    for name, arrays in {**cases, **planed}.items():
        names = ("leaf_codes",) if name in planed else ()
        (OUT / f"{name}.vxm").write_bytes(snapshot_bytes(base, arrays, codec="raw", planed=names))
        described = describe(base, arrays)
        if names:
            described["planed"] = list(names)
        (OUT / f"{name}.json").write_text(json.dumps(described, indent=1) + "\n")
    hashmap(base)


def hashmap(base: dict) -> None:
    """A hash map's snapshot (formats/snapshot.md, `hashmap` arrays): three voxels at 0.1 m, two
    occupied (in the history, oldest first: voxel 2, then voxel 0) and one undecided; voxel 0
    inflated a sphere of radius 2 voxels, voxel 2 one of radius 1 (an earlier d_inf)."""
    header = {**base, "backend": "hashmap", "map_params": {**base["map_params"], "resolution": 0.1},
              "backend_params": {"p_init": 0.5, "n_lim": 50000.0, "d_in": -1.0, "d_inf": 0.2, "inf_range": 8.0,
                                 "ttl": -1.0, "p_free": 0.4, "discretize": 1}}
    arrays = {"leaf_codes": np.array([0xE00000000000, 0xE00000000001, 0xE00000000008], np.int64),
              "leaf_depths": np.full(3, 16, np.uint8),
              "leaf_values": np.array([0.8472979, -0.2, 1.6945958], np.float32),
              "hm_radius": np.array([2, -1, 1], np.int32),
              "hm_last": np.array([300_000_000, 300_000_000, 100_000_000], np.int64),
              "hm_hits": np.array([2, 1, 4], np.int32), "hm_misses": np.array([0, 1, 2], np.int32),
              "hm_history": np.array([2, 0], np.int64)}
    (OUT / "snapshot_hashmap.vxm").write_bytes(snapshot_bytes(header, arrays, codec="raw"))
    (OUT / "snapshot_hashmap.json").write_text(json.dumps(describe(header, arrays), indent=1) + "\n")


def sharded() -> None:
    """A sharded map of 4 leaves in 2 partitions (formats/sharded.md), parts stored raw."""
    import hashlib

    from voxtool.distbuild import partition_of
    from voxtool.io.sharded import FORMAT, MANIFEST, VERSION, part_name
    from voxtool.maps.base import Leaves
    from voxtool.stats import leaf_stats

    out = OUT / "sharded_map"
    out.mkdir(parents=True, exist_ok=True)
    a = 0xE00000000000
    codes = np.array([a, a + 1, a + (2 << 18), a + (5 << 18)], np.int64)  # shards of depth 10: code >> 18
    depths = np.full(4, 16, np.uint8)
    values = np.array([0.8472979, -0.4054651, 0.8472979, -1.9924302], np.float32)
    part = partition_of(codes, 10, 2)
    assert set(part.tolist()) == {0, 1}
    header = {"voxtool_version": "0.1.0", "backend": "octree",
              "map_params": {"resolution": 0.2, "max_range": -1.0, "min_range": 0.0, "merge_rays": False},
              "sensor_model": {"prob_hit": 0.7, "prob_miss": 0.4, "clamp_min": 0.1192, "clamp_max": 0.971,
                               "occupancy_threshold": 0.5},
              "backend_params": {}}
    entries = []
    for p in range(2):
        keep = part == p
        arrays = {"leaf_codes": codes[keep], "leaf_depths": depths[keep], "leaf_values": values[keep]}
        blob = snapshot_bytes({**header, "info": {"source": "golden", "partition": p}}, arrays, codec="raw")
        (out / part_name(p)).write_bytes(blob)
        entries.append({"file": part_name(p), "bytes": len(blob), "sha256": hashlib.sha256(blob).hexdigest(),
                        "leaves": int(keep.sum()),
                        **leaf_stats(Leaves(codes[keep], depths[keep], values[keep]), 0.2, 0.0)})
    manifest = {"format": FORMAT, "version": VERSION, "partitions": 2, "shard_depth": 10,
                "partition_rule": "fibonacci-hash", "backend": "octree", "map_params": header["map_params"],
                "sensor_model": header["sensor_model"], "info": {"source": "golden", "scans": 1}, "parts": entries}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=True))
    (OUT / "sharded_map.json").write_text(json.dumps(
        {"leaf_codes": codes.tolist(), "leaf_depths": depths.tolist(), "leaf_values": values.tolist(),
         "partition": part.tolist()}, indent=1) + "\n")


def packets() -> None:
    from voxtool.codec.packet import KIND_KEYFRAME, decode_packet, encode_packet, occupied_frame
    from voxtool.keys import morton_encode

    keys = np.array([[32768, 32768, 32768], [32769, 32768, 32768], [32768, 32770, 32769]])
    states = np.array([0, 1, 2], np.uint8)
    line = np.array([[32768 + i, 32768 + i // 2, 32770] for i in range(7)] + [[32770, 32771, 32771]])
    line_states = np.array([0, 0, 0, 0, 0, 0, 1, 2], np.uint8)
    long_line = np.array([[32768 + i, 32772 + i // 3, 32770 + i // 2] for i in range(20)])
    long_states = np.array([0] * 19 + [1], np.uint8)
    cases = {
        "packet_hilbert": dict(scheme="hilbert", keys=keys, states=states),
        "packet_nested": dict(scheme="nested", keys=keys, states=states),
        "packet_racer": dict(scheme="racer", keys=keys, states=states,
                             box=(np.array([32768, 32768, 32768]), np.array([4, 4, 4]))),
        "packet_keyframe": dict(scheme="hilbert", keys=keys[:0], states=np.array([0, 1, 2, 0, 1, 1, 0, 2], np.uint8),
                                kind=KIND_KEYFRAME, box=(np.array([100, 200, 300]), np.array([2, 2, 2]))),
        "packet_occupied": dict(scheme="occupied", keys=keys[:0], states=states[:0],
                                frames=[(7, keys[:2]), (8, keys[2:])]),
        # cm1 (codec 3, the first cm coder): a short line of newly free voxels ending in a hit, one
        # voxel gone unknown (these bytes are the ones the first cm coder wrote as `packet_cm`)
        "packet_cm1": dict(scheme="nested", codec="cm1", keys=line, states=line_states),
        "packet_cm1_keyframe": dict(scheme="nested", codec="cm1", keys=keys[:0],
                                    states=np.array([0, 1, 2, 0, 1, 1, 0, 2, 2, 2, 0, 0], np.uint8), kind=KIND_KEYFRAME,
                                    box=(np.array([100, 200, 300]), np.array([3, 2, 2]))),
        # cm (codec 4): the same line, and a line that crosses 8^3 blocks (some left blank) in a box
        # of 20 x 12 x 10 cells
        "packet_cm": dict(scheme="nested", codec="cm", keys=line, states=line_states),
        "packet_cm_blocks": dict(scheme="nested", codec="cm", keys=np.concatenate([line, long_line]),
                                 states=np.concatenate([line_states, long_states])),
        "packet_cm_keyframe": dict(scheme="nested", codec="cm", keys=keys[:0],
                                   states=np.array([0, 1, 2, 0, 1, 1, 0, 2, 2, 2, 0, 0], np.uint8), kind=KIND_KEYFRAME,
                                   box=(np.array([100, 200, 300]), np.array([3, 2, 2]))),
    }
    for name, kw in cases.items():
        args = {"codec": "none", **kw}
        if "frames" in kw:  # encode_packet takes each frame as occupied_frame() bytes
            args["frames"] = [occupied_frame(f, morton_encode(k)) for f, k in kw["frames"]]
        blob = encode_packet("golden", 3, 1_700_000_000_000_000_000, resolution=0.1, **args)
        p = decode_packet(blob)
        desc = {"encode": {k: (v.tolist() if isinstance(v, np.ndarray) else
                               [x.tolist() for x in v] if k == "box" else
                               [[f, k2.tolist()] for f, k2 in v] if k == "frames" else v)
                           for k, v in kw.items()},
                "decoded": {"robot": p.robot, "seq": p.seq, "stamp_ns": p.stamp_ns, "scheme": p.scheme, "codec": p.codec,
                            "kind": p.kind, "box_min": list(p.box_min), "box_dims": list(p.box_dims), "count": p.count,
                            "voxels": sorted([*map(int, k), int(s)] for k, s in zip(p.keys, p.states))}}
        (OUT / f"{name}.bin").write_bytes(blob)
        (OUT / f"{name}.json").write_text(json.dumps(desc, indent=1) + "\n")


if __name__ == "__main__":
    main()
    packets()
    sharded()
