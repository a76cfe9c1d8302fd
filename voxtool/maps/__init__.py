"""Map backends. BACKENDS is the one registry the CLI and the snapshot loader read."""

from __future__ import annotations

from collections.abc import Callable

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.maps.base import MapBackend
from voxtool.maps.hashmap import HashVoxelMap
from voxtool.maps.octocache import OctoCacheMap
from voxtool.maps.octree import OctreeMap
from voxtool.maps.tiny import TinyMap

BACKENDS: dict[str, Callable[..., MapBackend]] = {
    "octree": OctreeMap,
    "octocache": OctoCacheMap,
    "tiny": TinyMap,
    "hashmap": HashVoxelMap,
}


def make_backend(name: str, params: MapParams, sensor: SensorModel, **options) -> MapBackend:
    try:
        factory = BACKENDS[name]
    except KeyError:
        raise ParameterError(f"backend '{name}' is not one of {', '.join(sorted(BACKENDS))}") from None
    try:
        return factory(params, sensor, **options)
    except TypeError as err:
        raise ParameterError(f"backend '{name}' does not take these options: {', '.join(sorted(options))}") from err
