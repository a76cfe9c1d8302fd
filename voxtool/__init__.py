"""voxtool: LiDAR scan streams to 3D occupancy voxel maps (docs/python.md).

    import voxtool
    m = voxtool.load("map.vxm")           # also an OctoMap .bt or a sharded map directory
    m.state([[1.0, 2.0, 0.5]])            # array(['occupied'], ...)
    voxtool.build("scans/", "map.vxm", resolution=0.2)
    for packet in voxtool.open_log("r1.mcap"): ...

Everything is imported on first use, so `import voxtool` (and `voxtool --help`) stays instant.
"""

from __future__ import annotations

__version__ = "0.1.0"
# the name on the package index (pip install), which is not the import name: "voxtool" there is
# another project's
DISTRIBUTION = "voxtool-lidar"
__all__ = ["build", "load", "open_log"]


def load(path):
    """A map (.vxm, a sharded map directory, or an OctoMap .bt) as a voxtool.voxelmap.VoxelMap."""
    from voxtool.voxelmap import load as _load

    return _load(path)


def build(source, output=None, *, resolution: float = 0.2, max_range: float = -1.0, backend: str = "octree",
          threads: int = 0, progress: bool = False, **source_options) -> dict:
    """Build a map from a scan source (as `voxtool build`); writes `output` (.vxm) if given.
    `source_options`: poses, topic, world_frame, pose_topic, start, stop, every, min_range.
    Returns the statistics and timings `voxtool build --json` prints."""
    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.sources import SourceOptions

    options = SourceOptions(**source_options)
    params = MapParams(resolution=resolution, max_range=max_range, min_range=options.min_range)
    return build_map(source, options, params, SensorModel(), backend, output, progress, {"threads": threads})


def open_log(path):
    """The packets of a packet log (.mcap), decoded (voxtool.codec.packet.Packet), in file order."""
    from voxtool.codec.log import read_log
    from voxtool.codec.packet import decode_packet

    _, messages = read_log(path)
    return (decode_packet(blob, f"{path}: packet of '{robot}'") for robot, _, blob in messages)
