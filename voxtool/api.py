"""Library entry points behind the CLI commands (usable from Python directly)."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.io.snapshot import ChunkedArrays
from voxtool.maps.base import Leaves, MapBackend
from voxtool.sources import SourceOptions, open_source, resolve_origin


def backend_stats(backend: MapBackend, tree: dict | None = None) -> dict:
    """A map's figures (docs/parameters.md): voxel counts and bounding box, the nodes of the
    two trees OctoMap has for it, and the bytes of the backend's own storage. `tree`: the
    figures of its leaves, when the caller has counted them (tree_stats)."""
    from voxtool.stats import tree_stats

    out = {"backend": backend.name, "resolution": backend.params.resolution}
    if tree is None:
        chunks = getattr(backend, "leaf_chunks", None)  # a large map's leaves, a chunk at a time
        tree = tree_stats(chunks() if chunks else backend.leaves(), backend.params.resolution,
                          backend.sensor.threshold_log, getattr(backend, "canonical_leaves", False))
    out.update(tree)
    out.update(pool_bytes=backend.memory_bytes(), pool_bytes_used=backend.used_bytes())
    out.update(backend.extra_stats())
    return out


RECORDED_COUNTS = ("scans", "points", "points_dropped", "raw_bytes")  # a build's counts kept in its snapshot


def build_map(source: str | os.PathLike, options: SourceOptions, params: MapParams, sensor: SensorModel,
              backend_name: str = "octree", output: str | os.PathLike | None = None,
              progress: bool | None = None, backend_options: dict | None = None,
              share: str | os.PathLike | None = None, share_ring: int = 3, robot: str = "r1",
              per_scan: bool = False) -> dict:
    """Build a map from a source; write a snapshot if `output` is given. Returns stats + timings.
    `share` (hashmap backend): write each scan's newly occupied voxels, ring of `share_ring`
    frames, as a packet log. `per_scan`: add each scan's latency, stamp and map bytes
    ("per_scan", the series of `build --plot`)."""
    from voxtool.atomic import check_writable
    from voxtool.maps import make_backend
    from voxtool.pipeline import build

    if output is not None and Path(output).suffix.lower() != ".vxm":
        raise ParameterError(f"{output}: map snapshots are written as .vxm (use `voxtool export` for .bt/.ply/.pcd/.png)")
    for path in (output, share):
        if path is not None:
            check_writable(path)
    t_start = time.perf_counter()
    startup = process_age()
    options = resolve_origin(source, options, params.resolution)
    stream = open_source(source, options)
    backend = make_backend(backend_name, params, sensor, **(backend_options or {}))
    writer = None
    if share is not None:
        from voxtool.codec.share import ShareWriter

        if backend_name != "hashmap":
            raise ParameterError("--share needs --backend hashmap (it shares the hash map's newly occupied voxels)")
        writer = ShareWriter(share, robot, share_ring, "zstd", params.resolution)
    ok = False
    try:
        with origin_hint(options):
            report = build(stream, backend, progress, writer)
        ok = True
    finally:
        if writer is not None:
            writer.close(ok)
    t_loop_end = time.perf_counter()
    counts = report.to_dict()
    tree, t_stats, t_write = None, 0.0, None
    if output is not None:
        tree, t_stats, t_write = save_counted(output, backend, snapshot_info(source, stream.kind, options, report))
    t0 = time.perf_counter()
    result = backend_stats(backend, tree)
    t_stats += time.perf_counter() - t0
    result.update(counts)
    result["origin"] = origin_of(options)
    result["threads"] = backend.threads
    if per_scan:
        result["per_scan"] = report.per_scan()
    if writer is not None:
        result["shared_bytes"] = writer.bytes
        result["shared_packets"] = writer.seq
    if t_write is not None:
        result["timings_s"]["write"] = round(t_write, 6)
    # where the rest of the command's time goes (docs/design/octree.md): before this call
    # (interpreter, imports, numba's set-up), opening the source and the map, the statistics
    result["timings_s"].update(startup=round(startup, 6) if startup is not None else None,
                               open=round(t_loop_end - t_start - report.time_total - report.time_jit, 6),
                               stats=round(t_stats, 6))
    return result


def snapshot_info(source: str | os.PathLike, kind: str, options: SourceOptions, report) -> dict:
    """What a map snapshot records of the build that made it (`report`: pipeline.build's):
    its source, the source's options, its counts, its last scan's stamp and its local origin."""
    counts = report.to_dict()
    return {"source": str(source), "source_kind": kind, "source_options": options.__dict__,
            **{k: counts[k] for k in RECORDED_COUNTS}, "last_stamp_ns": report.last_stamp_ns or 0,
            "origin": origin_of(options)}


def origin_of(options: SourceOptions) -> list[float]:
    """The map's local origin in the scans' frame (--origin), [0, 0, 0] without one: what
    snapshots record and `stats` reports; .bt files and packets are in the local frame."""
    return [float(v) for v in options.origin] if options.origin is not None else [0.0, 0.0, 0.0]


def local_frame_note(origin) -> str:
    """A picture's caption words for a map built about a local origin (--origin): its axes are
    not the scans' frame."""
    if origin is None or not any(origin):
        return ""
    return f" · axes in the map's local frame: add the origin ({', '.join(f'{v:.3f}' for v in origin)}) for the scans' frame"


@contextmanager
def origin_hint(options: SourceOptions):
    """A point beyond the key range: its error says how to build about a local origin."""
    from voxtool.errors import KeyRangeError

    try:
        yield
    except KeyRangeError as err:
        if options.origin is None:
            raise KeyRangeError(f"{err}; scans far from their frame's origin (a city or UTM frame) build about a "
                                "local origin with --origin auto") from err
        raise KeyRangeError(f"{err} (coordinates relative to --origin "
                            f"{','.join(f'{v:g}' for v in options.origin)}: the scans span more than the key range; "
                            "give a coarser --resolution or --max-range)") from err


def save_counted(output: str | os.PathLike, backend: MapBackend, info: dict) -> tuple[dict | None, float, float]:
    """save_map, counting the tree's figures (tree_stats) in the same pass when the backend's
    leaves go out a chunk at a time: (those figures, None otherwise; seconds counting; seconds
    writing besides)."""
    from voxtool.io.mapfile import save_map

    arrays = backend.state_arrays()
    leaves = arrays.get("leaf_codes")
    counter = None
    if isinstance(leaves, ChunkedArrays):
        from voxtool.stats import TreeStats

        counter = TreeStats(backend.sensor.threshold_log, getattr(backend, "canonical_leaves", False))
        arrays = dict.fromkeys(leaves.names, replace(leaves, chunks=lambda: counter.feed(leaves.chunks())))
    t0 = time.perf_counter()
    save_map(output, backend, info, arrays)
    seconds = time.perf_counter() - t0
    if counter is None:
        return None, 0.0, seconds
    return counter.result(backend.params.resolution), counter.seconds, seconds - counter.seconds


def process_age() -> float | None:
    """Seconds since this process started (Linux /proc; None elsewhere): what the interpreter,
    the imports and numba's set-up took before a command's work began."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return max(uptime - ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return None


def encode_log(source, output, options: SourceOptions, params: MapParams, sensor: SensorModel,
               backend_name: str, backend_options: dict, encode_options, progress: bool | None = None) -> dict:
    """Map `source` and write its voxel changes as a packet log (`voxtool encode`); the report
    carries the map's dropped-update figures, if any (dropped_warnings)."""
    from voxtool.atomic import check_writable
    from voxtool.codec.encode import encode_stream, robot_from_path
    from voxtool.maps import make_backend

    if encode_options.robot is None:  # no --robot: the log's name, so that two robots' logs never share one
        encode_options = replace(encode_options, robot=robot_from_path(output))
    if Path(output).suffix.lower() != ".mcap":
        raise ParameterError(f"{output}: packet logs are written as .mcap")
    check_writable(output)
    if backend_options.get("decay_half_life") is not None:
        # a packet carries the voxels a scan updated; decay changes voxels no scan touched
        raise ParameterError("decay_half_life is a build option: packet logs carry each scan's updates, not decay")
    mapper = make_backend(backend_name, params, sensor, **backend_options)
    options = resolve_origin(source, options, params.resolution)
    # every packet's map_origin field says where the map's keys sit in the scans' frame
    encode_options = replace(encode_options, map_origin=tuple(origin_of(options)))
    stream = open_source(source, options)
    info = {"source": str(source), "backend": backend_name, "origin": origin_of(options),
            "backend_params": {k: v for k, v in backend_options.items() if k != "schedule"},
            "map_params": params.to_dict(), "sensor_model": sensor.to_dict()}
    with origin_hint(options):
        result = encode_stream(stream, mapper, output, encode_options, info, progress)
    extra = mapper.extra_stats()
    result.update({k: extra[k] for k in DROP_FIGURES if extra.get(k)})
    return result


DROP_FIGURES = ("dropped_updates", "outside_map_updates", "pool_blocks", "map_size_m")


def dropped_warnings(where, figures: dict) -> list[str]:
    """One warning per kind of update a map dropped (the CLI prints them: never silent)."""
    of = f" of {figures['voxel_updates']:,}" if figures.get("voxel_updates") else ""
    out = []
    if figures.get("dropped_updates"):
        out.append(f"{where}: the tiny map's pool of {figures['pool_blocks']:,} blocks was full: "
                   f"{figures['dropped_updates']:,}{of} voxel updates were dropped; give --pool-blocks a larger budget, "
                   "or leave it out to size the pool from the map")
    if figures.get("outside_map_updates"):
        out.append(f"{where}: {figures['outside_map_updates']:,}{of} voxel updates fell outside the "
                   f"tiny map's {figures['map_size_m']:g} m extent and were dropped; give --map-size a larger extent")
    return out


def any_stats(path: str | os.PathLike, progress: bool | None = False) -> dict:
    """`voxtool stats` of one file: a packet log (.mcap), a sharded map (a directory), a
    snapshot or a .bt."""
    path = Path(path)
    if path.suffix.lower() == ".mcap":
        from voxtool.codec.logstats import log_stats

        return log_stats(path, progress)
    if path.is_dir():
        from voxtool.io.sharded import sharded_stats

        return sharded_stats(path, progress)
    return map_stats(path, progress)


def build_one_map(sources: list, options: SourceOptions, params: MapParams, sensor: SensorModel, client,
                  output: str | os.PathLike | None = None, sharded: bool = False, progress: bool | None = None,
                  shard_depth: int | None = None) -> dict:
    """One octree map from several sources on a Dask cluster (voxtool.distbuild), written as a
    snapshot, or as a sharded snapshot directory (`sharded`); returns stats + counts."""
    from voxtool.atomic import check_writable
    from voxtool.distbuild import distributed_build
    from voxtool.maps.shards import DEFAULT_SHARD_DEPTH, check_shard_depth

    depth = check_shard_depth(shard_depth if shard_depth is not None else DEFAULT_SHARD_DEPTH)
    options = resolve_origin(sources[0], options, params.resolution)  # auto: the first source's first scan
    info = {"source": [str(s) for s in sources] if len(sources) > 1 else str(sources[0]),
            "source_options": options.__dict__, "origin": origin_of(options)}
    if not sharded:
        if output is not None:
            if Path(output).suffix.lower() != ".vxm":
                raise ParameterError(f"{output}: one map is written as .vxm, or as a directory with --sharded")
            check_writable(output)
        backend, report = distributed_build(client, [str(s) for s in sources], options, params, sensor,
                                            shard_depth=depth, progress=progress)
        tree = None
        if output is not None:
            tree = save_counted(output, backend, {**info, **{k: report[k] for k in RECORDED_COUNTS},
                                                  "last_stamp_ns": report.get("last_stamp_ns") or 0})[0]
        result = backend_stats(backend, tree)
        result.update(report)
        return result
    from voxtool.io import sharded as S

    staging = S.staging_dir(output)
    try:
        entries, report = distributed_build(client, [str(s) for s in sources], options, params, sensor,
                                            shard_depth=depth, progress=progress, sharded_dir=staging, info=info)
        info.update({k: report[k] for k in RECORDED_COUNTS}, last_stamp_ns=report.get("last_stamp_ns") or 0)
        header = {"partitions": report["partitions"], "shard_depth": depth, "partition_rule": "fibonacci-hash",
                  "backend": "octree", "map_params": params.to_dict(), "sensor_model": sensor.to_dict(), "info": info}
        manifest = S.finish(staging, output, header, entries)
    except BaseException:
        S.abandon(staging)
        raise
    result = S.combined_stats(entries, manifest)  # the workers' figures of their parts: no second read
    result.update(report)
    return result


def load_leaves(path: str | os.PathLike) -> tuple[Leaves, float, float, dict]:
    """(leaves, resolution, threshold log-odds, info) of a .vxm snapshot or an OctoMap .bt file."""
    path = Path(path)
    if path.is_dir():  # the parts' stored leaves joined (rebuilding each part's tree, then the whole
        # tree took a kaist03 0.1 m .mcap export to 2.9 GB against 1.3 GB for the single snapshot)
        from voxtool.io.sharded import iter_part_leaves, read_manifest
        from voxtool.maps.base import join_leaves

        manifest = read_manifest(path)
        parts, threshold = [], SensorModel().threshold_log
        for _, part, part_threshold in iter_part_leaves(path):  # every part holds the map's sensor model
            parts.append(part)
            threshold = part_threshold
        recorded = manifest.get("info", {})
        info = {"backend": "octree", "info": {"last_stamp_ns": recorded.get("last_stamp_ns", 0),
                                              "origin": recorded.get("origin")}}
        return join_leaves(parts, consume=True), manifest["map_params"]["resolution"], threshold, info
    if path.suffix.lower() == ".bt":
        from voxtool.io.bt import read_bt

        tree = read_bt(path)
        sensor = SensorModel()
        values = np.where(tree.occupied, np.float32(sensor.clamp_max_log), np.float32(sensor.clamp_min_log))
        return Leaves(tree.codes, tree.depths, values.astype(np.float32)), tree.resolution, sensor.threshold_log, {
            "backend": "octomap-bt", "declared_nodes": tree.declared_size}
    from voxtool.io.mapfile import read_leaves

    return read_leaves(path)  # an octree snapshot's stored leaves, without rebuilding its tree


def map_origin(path: str | os.PathLike) -> list[float] | None:
    """The local origin a sharded map's manifest records (None: none, or not a sharded map)."""
    from voxtool.io.sharded import read_manifest

    if not Path(path).is_dir():
        return None
    origin = read_manifest(path).get("info", {}).get("origin")
    return origin if origin is not None and any(origin) else None


def map_stats(path: str | os.PathLike, progress: bool | None = False) -> dict:
    """Statistics of a snapshot (with the build counts recorded in it) or of a .bt file."""
    from voxtool.progress import bar
    from voxtool.stats import tree_stats

    path = Path(path)
    with bar(2, "stats", progress, "step") as steps:
        if path.suffix.lower() == ".bt":
            leaves, res, thr, meta = load_leaves(path)
            steps.update(1)
            out = {"backend": meta["backend"], "resolution": res}
            out.update(tree_stats(leaves, res, thr, False))
            # a .bt holds only the max-likelihood tree: no log-odds tree, no in-memory pool
            out.update(logodds_leaf_nodes=None, logodds_inner_nodes=None, pool_bytes=None, pool_bytes_used=None,
                       file_nodes=meta["declared_nodes"])
            return out
        from voxtool.io.mapfile import load_map

        backend, snap = load_map(path)
        steps.update(1)
        out = backend_stats(backend)
    info = snap.header.get("info", {})
    for key in ("scans", "points", "points_dropped"):
        if key in info:
            out[key] = info[key]
    out["voxtool_version"] = snap.header.get("voxtool_version")
    out["source"] = info.get("source")
    out["origin"] = info.get("origin", [0.0, 0.0, 0.0])
    return out


def exporter(output: Path):
    """The writer of an export file type (its suffix)."""
    from voxtool.io.export import EXPORTERS

    writer = EXPORTERS.get(output.suffix.lower())
    if writer is None:
        raise ParameterError(f"{output}: unknown export type '{output.suffix}' (use {', '.join(sorted(EXPORTERS))})")
    return writer


def crop_keys(box, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """The key box of the voxels whose centres lie in a metric box (xmin, ymin, zmin, xmax,
    ymax, zmax), inclusive."""
    from voxtool.keys import TREE_MAX_VAL, centre_key_range

    box = np.asarray(box, dtype=np.float64)
    if box.shape != (6,) or not np.all(np.isfinite(box)) or np.any(box[:3] > box[3:]):
        raise ParameterError(f"--crop {','.join(f'{v:g}' for v in np.ravel(box))}: give xmin,ymin,zmin,xmax,ymax,zmax "
                             "in metres, each min at most its max")
    lo, hi = centre_key_range(box[:3], box[3:], resolution)
    return np.clip(lo, 0, 2 * TREE_MAX_VAL - 1), np.clip(hi, -1, 2 * TREE_MAX_VAL - 1)


def export_scans(source: str | os.PathLike, output: str | os.PathLike, options: SourceOptions | None = None,
                 progress: bool | None = False) -> dict:
    """A scan source (any that `build` reads) written as an OctoMap ScanGraph (.graph), for
    OctoMap's own tools on the same input (sources.graph.write_graph)."""
    from voxtool.atomic import check_writable
    from voxtool.sources.graph import write_graph

    if Path(output).suffix.lower() != ".graph":
        raise ParameterError(f"{output}: scans are exported as an OctoMap .graph")
    check_writable(output)
    # about a local origin (--origin), the graph holds the shifted scans: OctoMap keeps float32 points and
    # poses. The origin snaps to whole metres, on the voxel grid of every resolution that divides 1 m.
    options = resolve_origin(source, options or SourceOptions(), 1.0)
    written = write_graph(output, open_source(source, options), progress)
    if options.origin is not None:
        written["origin"] = origin_of(options)
    return written


def export_map(path: str | os.PathLike, output: str | os.PathLike, include_free: bool = False,
               progress: bool | None = False, ros2_only: bool = False, view: str | None = None,
               slice_z: float | None = None, crop: tuple | None = None,
               z_range: tuple | None = None, above_ground: tuple | None = None,
               obstacle_threshold: float | None = None) -> dict:  # noqa: ARG001
    """Write a map (.vxm, .bt or a sharded map) as .bt, .ply, .pcd, .png, .mcap or .pgm (a 2D
    grid + its nav2 YAML); returns what was written. A sharded map is read part by part, except
    for .mcap, .vxm and .pgm and with `crop` (whole). `view` and `slice_z` are for pictures
    (io.picture); `crop` (xmin, ymin, zmin, xmax, ymax, zmax, metres): only the voxels whose
    centres lie in that box; `z_range` (min, max, metres): the heights a 2D grid (.pgm, .mcap)
    is projected from; `above_ground` (min, max, metres): the heights over the ground instead,
    with voxels over occupancy probability `obstacle_threshold` as obstacles (default: the map's
    threshold; docs/viewing.md). `ros2_only` changes nothing (every .mcap is ROS 2 now) and is kept for
    callers that pass it."""
    from voxtool.atomic import check_writable
    from voxtool.io.export import TAKES_ORIGIN, TAKES_Z_RANGE
    from voxtool.io.sharded_export import STREAMED, export_sharded
    from voxtool.progress import bar

    output = Path(output)
    kind = output.suffix.lower()
    if kind == ".vxm" and Path(path).suffix.lower() != ".bt":
        raise ParameterError(f"{output}: only an OctoMap .bt is imported as a snapshot ({path} is one already)")
    writer = exporter(output)
    check_writable(output)
    extra: dict = {}
    if view is not None or slice_z is not None:
        if kind != ".png":
            raise ParameterError(f"{output}: --view and --slice are for .png pictures")
        extra = {"view": view or "top", "slice_z": slice_z}
    if kind == ".png":
        extra["label"] = Path(path).name
    if z_range is not None:
        if kind not in TAKES_Z_RANGE:
            raise ParameterError(f"{output}: --z-range is for the 2D grid of a .pgm or .mcap")
        extra["z_range"] = tuple(z_range)
    if above_ground is not None:
        if kind not in (*TAKES_Z_RANGE, ".png"):
            raise ParameterError(f"{output}: --above-ground is for the 2D grid of a .pgm or .mcap, or a .png's colours")
        if z_range is not None:
            raise ParameterError("--z-range and --above-ground are two ways to choose heights: give one")
        extra["above_ground"] = tuple(above_ground)
    if obstacle_threshold is not None:
        if above_ground is None or kind not in TAKES_Z_RANGE:
            raise ParameterError(f"{output}: --obstacle-threshold is for the --above-ground grid of a .pgm or .mcap")
        if not 0.0 < obstacle_threshold < 1.0:
            raise ParameterError(f"--obstacle-threshold {obstacle_threshold:g} must be a probability between 0 and 1")
        from voxtool.config import logodds

        extra["obstacle_log"] = logodds(obstacle_threshold)
    if crop is not None:
        crop_keys(crop, 1.0)  # a bad box is refused before the map is read
    if Path(path).is_dir() and kind in STREAMED and crop is None and not map_origin(path) and above_ground is None:
        return export_sharded(path, output, include_free, progress, **extra)  # part by part
    if kind == ".png" and crop is None and Path(path).suffix.lower() == ".vxm" and above_ground is None:
        from voxtool.io.mapfile import stream_leaves

        streamed = stream_leaves(path)
        if streamed is not None:  # an octree snapshot, drawn a chunk of leaves at a time
            from voxtool.io.picture import write_leaf_sets

            res, thr, header, chunks = streamed
            extra["label"] += local_frame_note(header.get("info", {}).get("origin"))
            return write_leaf_sets(output, lambda: ((leaves, thr) for leaves in chunks()), res, include_free,
                                   progress=progress, **extra)
    with bar(2, f"export {output.suffix}", progress, "step") as steps:
        leaves, res, thr, meta = load_leaves(path)
        origin = meta.get("info", {}).get("origin")
        if kind in TAKES_ORIGIN and origin is not None and any(origin):
            extra["origin"] = tuple(origin)
        if kind == ".png":
            extra["label"] += local_frame_note(origin)
        if kind == ".mcap":  # stamped with the map's last scan (0: a map that does not say)
            extra["stamp_ns"] = int(meta.get("info", {}).get("last_stamp_ns", 0) or 0)
        if crop is not None:
            from voxtool.maps.tree import crop as crop_leaves

            leaves = crop_leaves(leaves, *crop_keys(crop, res))
            if kind == ".png":
                extra["below_roof"] = False  # the box chose the heights
            if kind == ".png" and len(leaves) == 0:
                raise ParameterError(f"{path}: no voxel of the map lies in --crop {','.join(f'{v:g}' for v in crop)}")
        if above_ground is not None:
            from voxtool.ground import check_has_height

            check_has_height(str(path), leaves, res, thr)
        steps.update(1)
        written = writer(output, leaves, res, thr, include_free, **extra)
        if obstacle_threshold is not None:
            written["obstacle_threshold"] = obstacle_threshold
        steps.update(1)
    return written


