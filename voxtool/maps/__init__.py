"""Map backends. BACKENDS is the one registry the CLI and the snapshot loader read."""

from __future__ import annotations

import importlib
import inspect
import typing
from collections.abc import Callable

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.maps.base import MapBackend

# name -> "module:class", imported when asked for: a command imports only its backend's kernels
# (all four cost an octree build 20 ms of start-up)
BACKENDS: dict[str, str | Callable[..., MapBackend]] = {
    "octree": "voxtool.maps.octree:OctreeMap",
    "octocache": "voxtool.maps.octocache:OctoCacheMap",
    "tiny": "voxtool.maps.tiny:TinyMap",
    "hashmap": "voxtool.maps.hashmap:HashVoxelMap",
}


def backend_class(name: str) -> Callable[..., MapBackend]:
    """The class of backend `name` (KeyError when there is none)."""
    entry = BACKENDS[name]
    if isinstance(entry, str):
        module, attr = entry.split(":")
        return getattr(importlib.import_module(module), attr)
    return entry


def make_backend(name: str, params: MapParams, sensor: SensorModel, **options) -> MapBackend:
    """The backend `name` with its options (from --param, or a snapshot's header) checked against
    its constructor: unknown names and values of the wrong kind are a ParameterError."""
    try:
        factory = backend_class(name)
    except KeyError:
        raise ParameterError(f"backend '{name}' is not one of {', '.join(sorted(BACKENDS))}") from None
    hints = typing.get_type_hints(factory.__init__)
    known = [k for k in inspect.signature(factory.__init__).parameters if k not in ("self", "params", "sensor")]
    unknown = sorted(set(options) - set(known))
    if unknown:
        takes = ", ".join(known) if known else "none"
        raise ParameterError(f"backend '{name}' has no option {', '.join(unknown)} (it takes {takes})")
    return factory(params, sensor, **{k: _coerce(name, k, v, hints.get(k)) for k, v in options.items()})


def _coerce(backend: str, key: str, value, hint):
    """value as the type the constructor declares: an integral float is an int; an int is a float."""
    allowed = typing.get_args(hint) or (hint,)
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if value is None and type(None) in allowed:
        return None
    if int in allowed and number and float(value).is_integer():
        return int(value)
    if float in allowed and number:
        return float(value)
    if (str in allowed and isinstance(value, str)) or (list in allowed and isinstance(value, list)):
        return value
    kind = "an integer" if int in allowed else "a number" if float in allowed else "text" if str in allowed else "a list"
    raise ParameterError(f"backend '{backend}': {key}={value!r} must be {kind}")
