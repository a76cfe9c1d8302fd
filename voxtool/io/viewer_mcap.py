"""Maps as MCAP that robotics viewers open (`voxtool export map.vxm -o map.mcap`), every message
a ROS 2 message (voxtool.io.ros2), so one file opens in Foxglove, rosbags and ROS 2 tools:

- `/voxtool/map`: a foxglove_msgs/msg/SceneUpdate: the occupied leaves of OctoMap's
  max-likelihood tree as cubes (pruned leaves as larger cubes), coloured by height; the free
  leaves as a second, translucent entity when asked for;
- `/projected_map`: a nav_msgs/msg/OccupancyGrid, the map projected to 2D (voxtool.grid), as
  octomap_server publishes it for a navigation stack;
- `/octomap_binary`: an octomap_msgs/msg/Octomap (binary, id OcTree, OctoMap's binary tree
  stream in `data`, as octomap_msgs' binaryMapToMsg fills it), for RViz's OctoMap plugin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.atomic import atomic_writer
from voxtool.io.picture import height_colours
from voxtool.keys import TREE_MAX_VAL, leaf_edge, morton_decode
from voxtool.maps.base import Leaves

FRAME = "map"
LOCAL_FRAME = "map_local"  # the octree's frame of a map built about a local origin (--origin)
GRID_TOPIC = "/projected_map"  # octomap_server's name for the 2D projection


def leaf_cubes(leaves: Leaves, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """(centres N x 3, edge lengths N) of leaves in metres."""
    span_keys = leaf_edge(leaves.depths).astype(np.float64)
    lo = morton_decode(leaves.codes).astype(np.float64) - TREE_MAX_VAL
    return (lo + span_keys[:, None] / 2) * resolution, span_keys * resolution


def scene_entity(entity_id: str, centres: np.ndarray, sizes: np.ndarray, rgba: np.ndarray, stamp_ns: int):
    """A foxglove_msgs/SceneEntity of cubes (one per centre), in frame `map`."""
    from voxtool.io.ros2 import msg, stamp

    Pose, Point, Vector3, Color = (msg(t) for t in ("geometry_msgs/msg/Pose", "geometry_msgs/msg/Point",
                                                     "geometry_msgs/msg/Vector3", "foxglove_msgs/msg/Color"))
    Cube, Quaternion = msg("foxglove_msgs/msg/CubePrimitive"), msg("geometry_msgs/msg/Quaternion")
    # one message object per cube (the serializer takes no bulk form): what all share (the
    # orientation; size and colour when uniform) is one object referenced by every cube
    identity = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    edges, size_of = np.unique(sizes, return_inverse=True)
    size_list = [Vector3(x=v, y=v, z=v) for v in edges.tolist()]
    colours, colour_of = np.unique(np.asarray(rgba, float).reshape(-1, 4), axis=0, return_inverse=True)
    colour_list = [Color(r=r, g=g, b=b, a=a) for r, g, b, a in colours.tolist()]
    size_of, colour_of = size_of.ravel().tolist(), colour_of.ravel().tolist()
    cubes = [Cube(pose=Pose(position=Point(x=x, y=y, z=z), orientation=identity), size=size_list[size_of[i]],
                  color=colour_list[colour_of[i]])
             for i, (x, y, z) in enumerate(centres.tolist())]
    return msg("foxglove_msgs/msg/SceneEntity")(
        timestamp=stamp(stamp_ns), frame_id=FRAME, id=entity_id, lifetime=msg("builtin_interfaces/msg/Duration")(
            sec=0, nanosec=0), frame_locked=False, metadata=[], arrows=[], cubes=cubes, spheres=[], cylinders=[],
        lines=[], triangles=[], texts=[], models=[])


def scene_message(entities: list, deletions: list | None = None):
    """A foxglove_msgs/SceneUpdate of entities (and deletions)."""
    from voxtool.io.ros2 import msg

    return msg("foxglove_msgs/msg/SceneUpdate")(deletions=deletions or [], entities=entities)


def scene_update(leaves: Leaves, resolution: float, threshold_log: float, include_free: bool, stamp_ns: int = 0,
                 entity_prefix: str = "", colour=None, origin=None):
    """A foxglove_msgs/SceneUpdate of the max-likelihood tree's leaves: entity `occupied` (by
    height, or one `colour`) and, with include_free, `free` (translucent); cube centres moved
    by the map's local origin into the scans' frame (float64, as geometry_msgs/Point holds)."""
    from voxtool.maps.tree import max_likelihood

    tree = max_likelihood(leaves, threshold_log)
    occupied = tree.values > 0
    entities = []
    shift = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    centres, sizes = leaf_cubes(Leaves(tree.codes[occupied], tree.depths[occupied], tree.values[occupied]), resolution)
    centres = centres + shift
    rgb = height_colours(centres[:, 2]) if colour is None else np.tile(np.asarray(colour, float), (len(sizes), 1))
    entities.append(scene_entity(f"{entity_prefix}occupied", centres, sizes,
                                        np.column_stack([rgb, np.ones(len(sizes))]), stamp_ns))
    if include_free:
        free = ~occupied
        centres, sizes = leaf_cubes(Leaves(tree.codes[free], tree.depths[free], tree.values[free]), resolution)
        centres = centres + shift
        rgba = np.tile([0.6, 0.85, 0.6, 0.08], (len(sizes), 1))
        entities.append(scene_entity(f"{entity_prefix}free", centres, sizes, rgba, stamp_ns))
    return scene_message(entities)


def octomap_message(leaves: Leaves, resolution: float, threshold_log: float, stamp_ns: int = 0, frame: str = FRAME):
    """The octomap_msgs/Octomap of the map (OctoMap's binary tree stream as data)."""
    from voxtool.io.bt import tree_stream

    return octomap_of_stream(tree_stream(leaves, threshold_log)[0], resolution, stamp_ns, frame)


def octomap_of_stream(body: bytes, resolution: float, stamp_ns: int = 0, frame: str = FRAME):
    """An octomap_msgs/Octomap holding OctoMap's binary tree stream `body`."""
    from voxtool.io.ros2 import msg, stamp

    header = msg("std_msgs/msg/Header")(stamp=stamp(stamp_ns), frame_id=frame)
    return msg("octomap_msgs/msg/Octomap")(header=header, binary=True, id="OcTree", resolution=float(resolution),
                                            data=np.frombuffer(body, dtype=np.int8))


def grid_message(grid, stamp_ns: int = 0, shift=(0.0, 0.0, 0.0)):
    """The nav_msgs/OccupancyGrid of a projected grid (voxtool.grid), in frame `map` (moved by
    the map's local origin `shift` into the scans' frame)."""
    from voxtool.io.ros2 import msg, stamp

    h, w = grid.cells.shape
    x, y, z = (float(grid.origin[0]) + float(shift[0]), float(grid.origin[1]) + float(shift[1]), float(shift[2]))
    origin = msg("geometry_msgs/msg/Pose")(
        position=msg("geometry_msgs/msg/Point")(x=x, y=y, z=z),
        orientation=msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0))
    info = msg("nav_msgs/msg/MapMetaData")(map_load_time=stamp(stamp_ns), resolution=float(grid.resolution),
                                           width=w, height=h, origin=origin)
    header = msg("std_msgs/msg/Header")(stamp=stamp(stamp_ns), frame_id=FRAME)
    return msg("nav_msgs/msg/OccupancyGrid")(header=header, info=info, data=grid.cells.ravel())


def local_frame_message(origin, stamp_ns: int):
    """/tf_static: frame `map` (the scans' frame) -> `map_local` (the octree's frame, at the
    map's local origin), so RViz places the Octomap, which can only be in the octree's frame."""
    from voxtool.io.ros2 import msg, stamp

    header = msg("std_msgs/msg/Header")(stamp=stamp(stamp_ns), frame_id=FRAME)
    transform = msg("geometry_msgs/msg/Transform")(
        translation=msg("geometry_msgs/msg/Vector3")(x=float(origin[0]), y=float(origin[1]), z=float(origin[2])),
        rotation=msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0))
    return msg("tf2_msgs/msg/TFMessage")(transforms=[msg("geometry_msgs/msg/TransformStamped")(
        header=header, child_frame_id=LOCAL_FRAME, transform=transform)])


def write_map_mcap(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
                   stamp_ns: int = 0, z_range: tuple | None = None, origin=None,
                   above_ground: tuple | None = None, obstacle_log: float | None = None) -> dict:
    """The map as one octomap_msgs/Octomap, one foxglove_msgs/SceneUpdate and one
    nav_msgs/OccupancyGrid (projected in `z_range`, as octomap_server's projected_map), all at
    `stamp_ns` (log time, header and entity stamps): the time of the last scan the map holds, 0
    if unknown. A map built about a local origin: the scene and the grid in the scans' frame
    (`map`), the Octomap in `map_local` with a /tf_static transform between the two."""
    from voxtool.ground import project_grid
    from voxtool.io.ros2 import Ros2McapWriter

    shifted = origin is not None and any(origin)
    update = scene_update(leaves, resolution, threshold_log, include_free, stamp_ns, origin=origin)
    octomap = octomap_message(leaves, resolution, threshold_log, stamp_ns, LOCAL_FRAME if shifted else FRAME)
    grid = project_grid(leaves, resolution, threshold_log, z_range, above_ground, obstacle_log) if len(leaves) else None
    with atomic_writer(path) as f:
        writer = Ros2McapWriter(f)
        if shifted:
            writer.write(writer.channel("/tf_static", "tf2_msgs/msg/TFMessage"), local_frame_message(origin, stamp_ns),
                         stamp_ns)
        writer.write(writer.channel("/octomap_binary", "octomap_msgs/msg/Octomap"), octomap, stamp_ns)
        writer.write(writer.channel("/voxtool/map", "foxglove_msgs/msg/SceneUpdate"), update, stamp_ns)
        if grid is not None:
            writer.write(writer.channel(GRID_TOPIC, "nav_msgs/msg/OccupancyGrid"),
                         grid_message(grid, stamp_ns, origin if shifted else (0.0, 0.0, 0.0)), stamp_ns)
        writer.finish()
    return {"format": "mcap", "topics": (["/tf_static"] if shifted else []) + ["/octomap_binary", "/voxtool/map"]
            + ([GRID_TOPIC] if grid else []),
            "cubes": {e.id: len(e.cubes) for e in update.entities}, "octomap_bytes": len(octomap.data),
            "grid": grid.counts() if grid else None, "stamp_ns": stamp_ns}


def write_grid_mcap(path: Path, grid, stamp_ns: int = 0, origin=None) -> dict:
    """A Grid2D alone as one nav_msgs/OccupancyGrid on GRID_TOPIC (frame `map`, the scans' frame:
    moved by a map's local `origin`), at `stamp_ns`; written atomically (`clean --grid`)."""
    from voxtool.io.ros2 import Ros2McapWriter

    shift = (0.0, 0.0, 0.0) if origin is None else tuple(float(v) for v in origin)
    with atomic_writer(path) as f:
        writer = Ros2McapWriter(f)
        writer.write(writer.channel(GRID_TOPIC, "nav_msgs/msg/OccupancyGrid"), grid_message(grid, stamp_ns, shift),
                     stamp_ns)
        writer.finish()
    return {"format": "mcap", "topics": [GRID_TOPIC], "origin": [grid.origin[0] + shift[0], grid.origin[1] + shift[1]],
            "stamp_ns": stamp_ns, **grid.counts()}
