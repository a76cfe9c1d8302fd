"""Exports and tree statistics of a sharded map, read part by part (memory: the largest part).

.bt: each part's max-likelihood subtrees are spooled to a temporary file beside the output,
then joined above the shards (io.sharded_tree) into OctoMap's stream: the same bytes as the
export of the whole map. .ply/.pcd: the header's point count comes from the manifest and is
checked against the points written. .png: one pass for the bounds, one to draw. .mcap: a
Foxglove SceneUpdate per part, the Octomap of the joined stream (as .bt), one OccupancyGrid
painted part by part (formats/sharded.md says what the file holds).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from voxtool.atomic import atomic_writer
from voxtool.errors import FormatError, ParameterError
from voxtool.io import sharded
from voxtool.io.sharded_tree import Units, add_part, join, write_pieces
from voxtool.progress import track

STREAMED = (".bt", ".ply", ".pcd", ".png", ".mcap")


def _parts(path: Path, progress, what: str):
    manifest = sharded.read_manifest(path)
    return manifest, track(sharded.iter_parts(path), len(manifest["parts"]), what, progress, "part")


def export_sharded(path: str | Path, output: Path, include_free: bool, progress: bool | None = False,
                   **picture) -> dict:
    """Write a sharded map as .bt, .ply, .pcd or .png (`picture`: io.picture's view options)
    without holding it whole."""
    path = Path(path)
    kind = output.suffix.lower()
    if kind == ".bt":
        return _bt(path, output, include_free, progress)
    if kind in (".ply", ".pcd"):
        return _cloud(path, output, kind[1:], include_free, progress)
    if kind == ".png":
        from voxtool.io.picture import picture_of_parts

        return picture_of_parts(path, output, include_free, progress, **picture)
    if kind == ".mcap":
        return _mcap(path, output, include_free, progress, picture.get("z_range"))
    raise ParameterError(f"{output}: a sharded map is exported part by part as {', '.join(STREAMED)}")


def _joined_tree(path: Path, spool, progress, what: str):
    """(resolution, leaf nodes, inner nodes, write(handle)): the whole map's OctoMap stream, its
    parts' max-likelihood subtrees spooled, joined above the shards; write() puts it on a handle."""
    from voxtool.maps.tree import max_likelihood

    units = Units()
    resolution = None
    _, parts = _parts(path, progress, what)
    for _, backend in parts:
        resolution = backend.params.resolution
        add_part(units, max_likelihood(backend.leaves(), backend.sensor.threshold_log), backend.shard_depth, spool)
    table = units.arrays()
    leaf_nodes, inner_nodes, pieces = join(table)
    return resolution, leaf_nodes, inner_nodes, lambda handle: write_pieces(handle, pieces, table, spool)


def _bt(path: Path, output: Path, include_free: bool, progress) -> dict:
    from voxtool.io.bt import HEADER

    if include_free:
        raise ParameterError(f"{output}: a .bt always holds free and occupied voxels; --free is for .ply/.pcd")
    with tempfile.TemporaryFile(dir=output.parent, prefix=".voxtool-spool-") as spool:
        resolution, leaf_nodes, inner_nodes, write = _joined_tree(path, spool, progress, "export .bt")
        header = (f"{HEADER.decode()}\n# (written by voxtool)\n#\nid OcTree\nsize {leaf_nodes + inner_nodes}\n"
                  f"res {resolution:.10g}\ndata\n").encode()
        with atomic_writer(output) as handle:
            handle.write(header)
            write(handle)
    return {"format": "bt", "bt_leaf_nodes": leaf_nodes, "bt_inner_nodes": inner_nodes}


def _mcap(path: Path, output: Path, include_free: bool, progress, z_range=None) -> dict:
    """The map .mcap of a sharded map with memory bounded by a part (and the Octomap's stream,
    one message by its type): the topics of the single map's file, a SceneUpdate per part."""
    import io

    from voxtool.grid import project_sets
    from voxtool.io.ros2 import Ros2McapWriter
    from voxtool.io.viewer_mcap import GRID_TOPIC, grid_message, octomap_of_stream, scene_update

    manifest = sharded.read_manifest(path)
    stamp_ns = int(manifest.get("info", {}).get("last_stamp_ns", 0) or 0)
    entries = manifest["parts"]

    def leaf_sets():
        for _, leaves, threshold in sharded.iter_part_leaves(path, check_hash=False):
            yield leaves, threshold

    cubes: dict[str, int] = {}
    with tempfile.TemporaryFile(dir=output.parent, prefix=".voxtool-spool-") as spool:
        resolution, _, _, write = _joined_tree(path, spool, progress, "export .mcap")
        stream = io.BytesIO()
        write(stream)
        octomap = octomap_of_stream(stream.getvalue(), resolution, stamp_ns)
        del stream
        grid = project_sets(leaf_sets, resolution, z_range)
        with atomic_writer(output) as f:
            writer = Ros2McapWriter(f)
            writer.write(writer.channel("/octomap_binary", "octomap_msgs/msg/Octomap"), octomap, stamp_ns)
            scene = writer.channel("/voxtool/map", "foxglove_msgs/msg/SceneUpdate")
            for entry, (leaves, threshold) in zip(entries, leaf_sets()):
                update = scene_update(leaves, resolution, threshold, include_free, stamp_ns,
                                      entity_prefix=f"{Path(entry['file']).stem}/")
                writer.write(scene, update, stamp_ns)
                cubes.update({e.id: len(e.cubes) for e in update.entities})
            writer.write(writer.channel(GRID_TOPIC, "nav_msgs/msg/OccupancyGrid"), grid_message(grid, stamp_ns),
                         stamp_ns)
            writer.finish()
    return {"format": "mcap", "topics": ["/octomap_binary", "/voxtool/map", GRID_TOPIC], "cubes": cubes,
            "octomap_bytes": len(octomap.data), "grid": grid.counts(), "stamp_ns": stamp_ns,
            "scene_messages": len(entries)}


def _cloud(path: Path, output: Path, fmt: str, include_free: bool, progress) -> dict:
    from voxtool.io.export import CLOUD_FORMATS, _cloud

    header, rows = CLOUD_FORMATS[fmt]
    manifest = sharded.read_manifest(path)
    occupied = sum(int(e.get("occupied_voxels", 0)) for e in manifest["parts"])
    declared = occupied + (sum(int(e.get("free_voxels", 0)) for e in manifest["parts"]) if include_free else 0)
    written = 0
    with atomic_writer(output) as handle:
        handle.write(header(declared, include_free))
        _, parts = _parts(path, progress, f"export .{fmt}")
        for _, backend in parts:
            pts, colors = _cloud(backend.leaves(), backend.params.resolution, backend.sensor.threshold_log, include_free)
            written += len(pts)
            handle.write(rows(pts, colors))
        if written != declared:  # the file is discarded
            raise FormatError(f"{path}: its parts hold {written} voxels to write, the manifest {declared}")
    return {"format": fmt, "points": written, "occupied_voxels": occupied,
            "free_voxels": written - occupied if include_free else None}
