"""The bad-input corpus: every case builds its input in code (no binary blobs checked in).

Each case: (name, builder(tmp) -> CLI arguments, exit code, exact message fragment). The
builders write into `tmp`; the output file each command would write is `tmp/out.*`.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
from scenes import box_scene, lzf_literal, write_pcd, yaw_quat

PTS = box_scene(1, 40, seed=2)[0][0]


def pcd_bytes(kind="binary", fields="x y z", size="4 4 4", types="F F F", count="1 1 1", width=None, height=1,
              points=None, viewpoint="0 0 0 1 0 0 0", body=None, n=len(PTS), extra=""):
    width = n if width is None else width
    points = width * height if points is None else points
    head = "# .PCD v0.7\nVERSION 0.7\n"
    for key, value in (("FIELDS", fields), ("SIZE", size), ("TYPE", types), ("COUNT", count)):
        if value is not None:
            head += f"{key} {value}\n"
    head += f"WIDTH {width}\nHEIGHT {height}\n"
    if viewpoint is not None:
        head += f"VIEWPOINT {viewpoint}\n"
    head += f"POINTS {points}\n{extra}DATA {kind}\n"
    if body is None:
        body = PTS[:n].astype("<f4").tobytes()
    return head.encode() + body


def scans_dir(tmp: Path, blob: bytes, name="0.pcd") -> Path:
    d = tmp / "scans"
    d.mkdir(exist_ok=True)
    (d / name).write_bytes(blob)
    return d


def build(tmp: Path, source: Path, *extra) -> list:
    return ["build", source, "-o", tmp / "out.vxm", *extra]


def pcd_case(**kw):
    return lambda tmp: build(tmp, scans_dir(tmp, pcd_bytes(**kw)))


def compressed(csize_delta=0, usize_delta=0, mutate=None, short=False):
    raw = np.ascontiguousarray(PTS.astype("<f4").T).tobytes()
    comp = lzf_literal(raw)
    if mutate:
        comp = mutate(comp)
    body = struct.pack("<II", len(comp) + csize_delta, len(raw) + usize_delta) + comp
    if short:
        body = body[:5]
    return pcd_case(kind="binary_compressed", body=body)


def ply_case(text_head: str, body: bytes | None = None, poses=True):
    def make(tmp):
        d = tmp / "scans"
        d.mkdir()
        data = text_head.encode() + (body if body is not None else PTS.astype("<f4").tobytes())
        (d / "0.ply").write_bytes(data)
        (tmp / "p.txt").write_text("0 0 0 0 0 0 0 1\n")
        return build(tmp, d, *(["--poses", tmp / "p.txt"] if poses else []))
    return make


PLY_HEAD = "ply\nformat binary_little_endian 1.0\nelement vertex 40\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def pose_case(text: str, n_scans=2):
    def make(tmp):
        d = tmp / "scans"
        d.mkdir()
        for i in range(n_scans):
            write_pcd(d / f"{i}.pcd", PTS)
        (tmp / "p.txt").write_text(text)
        return build(tmp, d, "--poses", tmp / "p.txt")
    return make


def mcap_case(overrides=None, skip_tf=False, extra=(), mutate=None):
    def make(tmp):
        from ros2_writer import write_mcap

        scans = [(p, o, yaw_quat(y)) for p, o, y in box_scene(3, 30, seed=1)]
        path = tmp / "in.mcap"
        write_mcap(path, scans, cloud_overrides=overrides, skip_tf=skip_tf)
        if mutate:
            path.write_bytes(mutate(path.read_bytes()))
        return build(tmp, path, *extra)
    return make


def graph_case(mutate):
    def make(tmp):
        from ros2_writer import write_graph

        scans = [(p, o, yaw_quat(y)) for p, o, y in box_scene(2, 30, seed=1)]
        path = tmp / "in.graph"
        write_graph(path, scans)
        path.write_bytes(mutate(path.read_bytes()))
        return build(tmp, path)
    return make


def _sample_snapshot(tmp: Path) -> bytes:
    from voxtool.config import MapParams, SensorModel
    from voxtool.io.mapfile import save_map
    from voxtool.maps.octree import OctreeMap
    from voxtool.sources.scan import Scan

    m = OctreeMap(MapParams(0.2), SensorModel())
    m.integrate(Scan(np.array([[1.0, 1.0, 0.5], [2.0, -1.0, 0.3]], np.float32), np.zeros(3, np.float32)))
    save_map(tmp / "good.vxm", m, {})
    return (tmp / "good.vxm").read_bytes()


def snapshot_case(mutate, command="stats"):
    def make(tmp):
        blob = mutate(_sample_snapshot(tmp))
        (tmp / "in.vxm").write_bytes(blob)
        if command == "export":
            return ["export", tmp / "in.vxm", "-o", tmp / "out.bt"]
        return ["stats", tmp / "in.vxm"]
    return make


def recrc(blob: bytes) -> bytes:
    return blob[:-4] + struct.pack("<I", zlib.crc32(blob[:-4]))


def snapshot_with(header_edit=None, arrays=None):
    """A snapshot whose header or arrays are replaced, with valid CRCs (semantic corruption)."""
    def mutate(blob):
        from voxtool.io.snapshot import parse_snapshot, snapshot_bytes

        snap = parse_snapshot(blob)
        header = {k: v for k, v in snap.header.items() if k != "arrays"}
        if header_edit:
            header_edit(header)
        arrs = dict(snap.arrays)
        if arrays:
            arrays(arrs)
        return snapshot_bytes(header, arrs)
    return mutate


def declared_size_too_large(blob: bytes) -> bytes:
    import json

    head_len = struct.unpack_from("<I", blob, 12)[0]
    header = json.loads(blob[16 : 16 + head_len])
    header["arrays"][0]["raw_bytes"] = 1 << 40
    header["arrays"][0]["shape"] = [1 << 37]
    new_head = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    body = blob[:12] + struct.pack("<I", len(new_head)) + new_head + blob[16 + head_len : -4]
    return recrc(body + b"\0\0\0\0")


def packet_log_case(mutate=None, blob_edit=None, scheme="hilbert", codec="zstd"):
    def make(tmp):
        from voxtool.codec.log import PacketLogWriter
        from voxtool.codec.packet import encode_packet

        path = tmp / "in.mcap"
        blob = encode_packet("r", 0, 10, scheme, codec, 0.1, np.array([[5, 5, 5], [6, 6, 6]]), np.array([0, 1], np.uint8))
        if blob_edit:
            blob = blob_edit(blob)
        with PacketLogWriter(path) as log:
            log.write("r", 0, 10, blob)
        if mutate:
            path.write_bytes(mutate(path.read_bytes()))
        return ["decode", path, "-o", tmp / "out.vxm"]
    return make


def huge_box(blob: bytes) -> bytes:
    from voxtool.codec.packet import HEADER

    f = list(HEADER.unpack_from(blob, 0))
    f[15:18] = [65535, 65535, 65535]
    f[12:15] = [0, 0, 0]
    f[19] = 1 << 29
    head = HEADER.pack(*f)
    payload = blob[HEADER.size :]
    crc = zlib.crc32(payload, zlib.crc32(head[:-4]))
    return head[:-4] + struct.pack("<I", crc) + payload


def resealed(blob: bytes, payload: bytes | None = None, **fields) -> bytes:
    """The packet with header fields (by HEADER index) and payload replaced, its stored size and
    CRC made right again: the decoder must find what is wrong behind a valid CRC."""
    from voxtool.codec.packet import HEADER

    f = list(HEADER.unpack_from(blob, 0))
    for index, value in fields.items():
        f[int(index[1:])] = value
    payload = blob[HEADER.size :] if payload is None else payload
    f[20] = len(payload)
    head = HEADER.pack(*f)
    return head[:-4] + struct.pack("<I", zlib.crc32(payload, zlib.crc32(head[:-4]))) + payload


def far_point(tmp):
    write_pcd_dir = tmp / "scans"
    write_pcd_dir.mkdir()
    write_pcd(write_pcd_dir / "0.pcd", np.array([[1.0, 0, 0], [0, 7000.0, 0]], np.float32))
    return build(tmp, write_pcd_dir)


def far_origin(tmp):
    d = tmp / "scans"
    d.mkdir()
    write_pcd(d / "0.pcd", PTS, viewpoint=(9000.0, 0, 0, 1, 0, 0, 0))
    return build(tmp, d)


def lzf_bad_ref(comp: bytes) -> bytes:
    # a back reference (ctrl >= 32) as the first token points before the output start
    return bytes([0x20, 0x05]) + comp


def lzf_overflow(comp: bytes) -> bytes:
    return comp + bytes([0x1F]) + b"\0" * 32


CASES = [
    # --- PCD -----------------------------------------------------------------------------
    ("pcd truncated binary body", lambda t: build(t, scans_dir(t, pcd_bytes()[:-10])), 3, "PCD binary body has 470 bytes, header declares 480"),
    ("pcd without FIELDS", pcd_case(fields=None), 3, "PCD header lacks FIELDS"),
    ("pcd without SIZE", pcd_case(size=None), 3, "PCD header lacks SIZE"),
    ("pcd without TYPE", pcd_case(types=None), 3, "PCD header lacks TYPE"),
    ("pcd FIELDS/SIZE disagree", pcd_case(size="4 4"), 3, "FIELDS/SIZE/TYPE/COUNT disagree in length (3/2/3/3)"),
    ("pcd unsupported type", pcd_case(size="2 4 4"), 3, "field 'x' has unsupported TYPE F SIZE 2"),
    ("pcd POINTS contradicts WIDTH", pcd_case(points=41), 3, "PCD POINTS 41 != WIDTH 40 x HEIGHT 1"),
    ("pcd without z", pcd_case(fields="x y w"), 3, "PCD has no 'z' field"),
    ("pcd unknown DATA", pcd_case(kind="binary_lz4"), 3, "PCD DATA 'binary_lz4' is not ascii, binary or binary_compressed"),
    ("pcd non-numeric WIDTH", pcd_case(width="forty"), 3, "PCD header WIDTH is not a list of integers"),
    ("pcd 10^8 points", pcd_case(width=100_000_000), 3, "declares 100000000 points, more than the limit of 50000000"),
    ("pcd short VIEWPOINT", pcd_case(viewpoint="0 0 0 1 0 0"), 3, "VIEWPOINT needs 7 finite numbers"),
    ("pcd NaN VIEWPOINT", pcd_case(viewpoint="nan 0 0 1 0 0 0"), 3, "VIEWPOINT needs 7 finite numbers"),
    ("pcd zero quaternion", pcd_case(viewpoint="0 0 0 0 0 0 0"), 3, "VIEWPOINT quaternion is zero"),
    ("pcd without DATA", lambda t: build(t, scans_dir(t, b"VERSION 0.7\nFIELDS x y z\n" + b"\xff" * 200)), 3, "inside its PCD header, before the DATA line"),
    ("pcd empty file", lambda t: build(t, scans_dir(t, b"")), 3, "the file is empty (0 bytes)"),
    ("pcd bad COUNT", pcd_case(count="1 1 0"), 3, "field 'z' has COUNT 0"),
    ("pcd ascii non-numeric", pcd_case(kind="ascii", body=b"1 2 x\n" * 40), 3, "PCD ascii body holds a non-numeric value"),
    ("pcd ascii too few values", pcd_case(kind="ascii", body=b"1 2 3\n" * 39), 3, "PCD ascii body has 117 values, header declares 40 x 3"),
    ("pcd ascii too many values", pcd_case(kind="ascii", body=b"1 2 3\n" * 41), 3, "PCD ascii body has 123 values, header declares 40 x 3"),
    ("pcd compressed short size header", compressed(short=True), 3, "shorter than its 8-byte size header"),
    ("pcd compressed wrong uncompressed size", compressed(usize_delta=4), 3, "declares 484 uncompressed bytes, expected 480"),
    ("pcd compressed size beyond file", compressed(csize_delta=100), 3, "declares 595 compressed bytes, file holds 495"),
    ("pcd LZF truncated", compressed(mutate=lambda c: c[:-5], csize_delta=0), 3, "LZF data is corrupt (truncated)"),
    ("pcd LZF bad back reference", compressed(mutate=lzf_bad_ref), 3, "LZF data is corrupt (bad back reference)"),
    ("pcd LZF output overflow", compressed(mutate=lzf_overflow), 3, "LZF data is corrupt (output larger than declared)"),
    # --- PLY -----------------------------------------------------------------------------
    ("ply without magic", ply_case("plx\n" + PLY_HEAD[4:]), 3, "not a PLY file"),
    ("ply without end_header", ply_case(PLY_HEAD.replace("end_header\n", ""), b""), 3, "PLY header has no end_header"),
    ("ply unknown format", ply_case(PLY_HEAD.replace("binary_little_endian", "binary_middle_endian")), 3, "PLY format 'binary_middle_endian' is not ascii or binary"),
    ("ply short body", ply_case(PLY_HEAD, PTS.astype("<f4").tobytes()[:-12]), 3, "PLY body has 468 bytes, header declares 480"),
    ("ply without vertex", ply_case(PLY_HEAD.replace("element vertex", "element face")), 3, "PLY has no 'vertex' element"),
    ("ply without z", ply_case(PLY_HEAD.replace("property float z", "property float w")), 3, "PLY vertex element has no 'z' property"),
    ("ply bad property", ply_case(PLY_HEAD.replace("property float z", "property quaternion z")), 3, "PLY property line not understood"),
    ("ply ascii non-numeric", ply_case(PLY_HEAD.replace("binary_little_endian", "ascii"), b"1 2 q\n" * 40), 3, "PLY ascii body holds a non-numeric value"),
    ("ply list in vertex", ply_case(PLY_HEAD.replace("property float z", "property float z\nproperty list uchar int idx")), 3, "PLY vertex element with list properties is not supported"),
    ("ply non-integer count", ply_case(PLY_HEAD.replace("vertex 40", "vertex forty")), 3, "PLY element count 'forty' is not an integer"),
    ("ply without poses", ply_case(PLY_HEAD, poses=False), 3, "PLY scans need a pose file (--poses)"),
    # --- pose files ----------------------------------------------------------------------
    ("poses wrong row count", pose_case("0 0 0 0 0 0 0 1\n"), 3, "pose file has 1 poses for 2 scans"),
    ("poses non-unit quaternion", pose_case("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1.5\n"), 3, "p.txt:2: quaternion has norm 1.500000"),
    ("poses non-numeric", pose_case("0 0 0 0 0 0 0 1\n1 a 0 0 0 0 0 1\n"), 3, "p.txt:2: pose row is not numeric"),
    ("poses 7 columns", pose_case("0 0 0 0 0 0 1\n" * 2), 3, "pose row has 7 numbers; expected 8 (TUM), 9 (index + TUM) or 12 (KITTI)"),
    ("poses ragged rows", pose_case("0 0 0 0 0 0 0 1\n0 1 0 0 0 0 0 0 1\n"), 3, "p.txt:2: pose row has 9 numbers, earlier rows have 8"),
    ("poses KITTI not orthonormal", pose_case("2 0 0 0 0 1 0 0 0 0 1 0\n" * 2), 3, "KITTI rotation is not orthonormal"),
    ("poses NaN", pose_case("0 nan 0 0 0 0 0 1\n" * 2), 3, "pose row holds NaN or inf"),
    ("poses empty", pose_case("# nothing\n"), 3, "pose file holds no poses"),
    # --- MCAP ----------------------------------------------------------------------------
    ("mcap truncated", mcap_case(mutate=lambda b: b[: len(b) // 2]), 3,
     "cannot be read as MCAP: a record declares more bytes than any record may hold: the file is truncated"),
    ("mcap not mcap", mcap_case(mutate=lambda b: b"hello world" * 10), 3,
     "cannot be read as MCAP: it does not start (or end) with the MCAP magic"),
    ("mcap without the topic", mcap_case(extra=("--topic", "/lidar")), 3, "topic '/lidar' is not a PointCloud2, LaserScan or VelodyneScan topic (those topics: /points)"),
    ("mcap without transforms", mcap_case(skip_tf=True), 3, "no transform reaches the scan frame 'lidar' (the log has no /tf transform); pose them with --world-frame lidar"),
    ("mcap point_step beyond row_step", mcap_case(overrides={"point_step": 16}), 3, "point_step 16 x width 30 exceeds row_step 360"),
    ("mcap row_step beyond data", mcap_case(overrides={"row_step": 400}), 3, "data has 360 bytes, row_step x height needs 400"),
    ("mcap field beyond point_step", mcap_case(overrides={"fields": [{"name": "x", "offset": 0, "datatype": 7, "count": 1}, {"name": "y", "offset": 4, "datatype": 7, "count": 1}, {"name": "z", "offset": 10, "datatype": 7, "count": 1}]}), 3, "field 'z' at offset 10 does not fit point_step 12"),
    ("mcap cloud without z", mcap_case(overrides={"fields": [{"name": "x", "offset": 0, "datatype": 7, "count": 1}, {"name": "y", "offset": 4, "datatype": 7, "count": 1}]}), 3, "has no 'z' field"),
    ("mcap unknown datatype", mcap_case(overrides={"fields": [{"name": "x", "offset": 0, "datatype": 9, "count": 1}, {"name": "y", "offset": 4, "datatype": 7, "count": 1}, {"name": "z", "offset": 8, "datatype": 7, "count": 1}]}), 3, "field 'x' has unknown datatype 9"),
    ("mcap missing pose topic", mcap_case(extra=("--pose-topic", "/odom")), 3, "pose topic '/odom' is not Odometry, PoseStamped, PoseWithCovarianceStamped or TransformStamped"),
    # --- ScanGraph -----------------------------------------------------------------------
    ("graph truncated points", graph_case(lambda b: b[:500]), 3, "declares 30 points, beyond the file or the limit"),
    ("graph too many nodes", graph_case(lambda b: struct.pack("<I", 10**6) + b[4:]), 3, "declares 1000000 nodes"),
    ("graph bad Vector3 size", graph_case(lambda b: b[:8] + struct.pack("<i", 4) + b[12:]), 3, "Vector3 size field is not 3"),
    ("graph truncated pose", graph_case(lambda b: b[: 8 + 30 * 28 + 20]), 3, "truncated in node 0 (pose)"),
    ("graph shorter than count", graph_case(lambda b: b[:2]), 3, "shorter than its 4-byte node count"),
    # --- key range -----------------------------------------------------------------------
    ("point outside key range", far_point, 4, "point 1 at (0.0, 7000.0, 0.0) lies outside the octree key range (|coordinate| < 6553.6 m"),
    ("origin outside key range", far_origin, 4, "sensor origin of scan 0 at (9000.0, 0.0, 0.0) lies outside the octree key range"),
    # --- snapshots -----------------------------------------------------------------------
    ("snapshot truncated", snapshot_case(lambda b: b[: len(b) - 20]), 5, "CRC mismatch (file is corrupt or truncated)"),
    ("snapshot bit flip", snapshot_case(lambda b: b[:60] + bytes([b[60] ^ 4]) + b[61:]), 5, "CRC mismatch"),
    ("snapshot future version", snapshot_case(lambda b: b[:8] + struct.pack("<H", 2) + b[10:]), 5, "snapshot format version 2 is newer than this voxtool reads (1)"),
    ("snapshot bad magic", snapshot_case(lambda b: b"\x89VXN" + b[4:]), 5, "not a voxtool snapshot (bad magic)"),
    ("snapshot header beyond file", snapshot_case(lambda b: b[:12] + struct.pack("<I", 1 << 19) + b[16:]), 5, "header length 524288 exceeds the file"),
    ("snapshot declares 1 TiB array", snapshot_case(declared_size_too_large), 5, "declares 1099511627776 bytes for shape [137438953472]"),
    ("snapshot unsorted leaves", snapshot_case(snapshot_with(arrays=lambda a: a.update(leaf_codes=a["leaf_codes"][::-1].copy(), leaf_depths=a["leaf_depths"][::-1].copy(), leaf_values=a["leaf_values"][::-1].copy()))), 5, "leaves are not sorted or overlap"),
    ("snapshot leaf depth 17", snapshot_case(snapshot_with(arrays=lambda a: a.update(leaf_depths=np.full_like(a["leaf_depths"], 17)))), 5, "leaf depth 17 is not 0..16"),
    ("snapshot NaN log-odds", snapshot_case(snapshot_with(arrays=lambda a: a.update(leaf_values=np.full_like(a["leaf_values"], np.nan)))), 5, "leaf log-odds not finite"),
    ("snapshot unknown backend", snapshot_case(snapshot_with(header_edit=lambda h: h.update(backend="quadtree"))), 5, "backend 'quadtree' is not one of"),
    ("snapshot bad resolution", snapshot_case(snapshot_with(header_edit=lambda h: h["map_params"].update(resolution=-1))), 5, "resolution=-1 must lie in"),
    ("snapshot truncated, export", snapshot_case(lambda b: b[:100], command="export"), 5, "exceeds the file (100 bytes) or the 1 MiB limit"),
    # --- packet logs ---------------------------------------------------------------------
    ("packet log truncated", packet_log_case(mutate=lambda b: b[: len(b) // 2]), 5, "cannot be read as a packet log: "),
    ("packet log junk", packet_log_case(mutate=lambda b: b"\x89MCAP0\r\n" + b"\0" * 40), 5, "cannot be read as a packet log: "),
    ("packet with bad CRC", packet_log_case(blob_edit=lambda b: b[:-1] + bytes([b[-1] ^ 1])), 5, "packet of 'r': CRC mismatch"),
    ("packet declares 4 GB box", packet_log_case(blob_edit=huge_box), 5, "exceeds the key range or 2147483648 cells"),
    ("packet future version", packet_log_case(blob_edit=lambda b: b[:4] + bytes([7]) + b[5:]), 5, "packet version 7 is not supported"),
    ("packet cm stream truncated", packet_log_case(blob_edit=lambda b: resealed(b, b[96:-1]), scheme="nested", codec="cm"), 5,
     "packet of 'r': cm stream is truncated"),
    ("packet cm stream with a trailing byte", packet_log_case(blob_edit=lambda b: resealed(b, b[96:] + b"\0"), scheme="nested",
                                                           codec="cm"), 5, "cm stream has 1 trailing bytes"),
    ("packet cm in hilbert order", packet_log_case(blob_edit=lambda b: resealed(b, f3=0), scheme="nested", codec="cm"), 5,
     "codec cm with scheme hilbert"),
    ("packet cm box too large for its stream", packet_log_case(
        blob_edit=lambda b: resealed(b, f15=4000, f16=4000, f17=100, f19=(4000 * 4000 * 100 + 3) // 4),
        scheme="nested", codec="cm"), 5, "a cm stream of 6 bytes cannot hold a box of (4000, 4000, 100) cells"),
    ("packet cm1 box too large for its stream", packet_log_case(
        blob_edit=lambda b: resealed(b, f15=4000, f16=4000, f17=100, f19=(4000 * 4000 * 100 + 3) // 4),
        scheme="nested", codec="cm1"), 5, "cannot hold a box of 1600000000 cells"),
    ("packet cm with more cells than declared", packet_log_case(blob_edit=lambda b: resealed(b, f18=1),
                                                                scheme="nested", codec="cm"), 5,
     "cm stream holds more than the 1 cells the packet declares"),
]


def flip_in_first_chunk(blob: bytes) -> bytes:
    """Flip a byte in the middle of the first chunk record (opcode 0x06) of an MCAP file."""
    i = blob.index(b"\x06", 8)
    j = i + 9 + 200
    return blob[:j] + bytes([blob[j] ^ 0x40]) + blob[j + 1 :]


def mcap_without_schema(tmp):
    from mcap.writer import Writer

    path = tmp / "in.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        ch = w.register_channel("/points", "cdr", 0)  # schema id 0: no schema
        w.add_message(ch, 0, b"\0" * 64, 0)
        w.finish()
    return build(tmp, path)


CASES += [
    ("mcap chunk corrupted", mcap_case(mutate=flip_in_first_chunk), 3, "cannot read its poses: a CRC does not match"),
    ("mcap channel without schema", mcap_without_schema, 3, "no PointCloud2 or LaserScan topic to build from"),
]


def missing_output_dir(tmp):
    d = tmp / "scans"
    d.mkdir()
    write_pcd(d / "0.pcd", PTS)
    return ["build", d, "-o", tmp / "no" / "such" / "dir" / "out.vxm"]


CASES += [
    ("output directory missing", missing_output_dir, 1, "output directory"),
]
