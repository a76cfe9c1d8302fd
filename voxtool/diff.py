"""`voxtool diff A B`: where two maps differ (docs/diff.md).

Both maps are read as leaves and compared as runs of Morton codes (kernels.diff): counts of
voxels per state change (unknown / free / occupied, each map by its own threshold), OctoMap's
compare_octrees KL divergence over the voxels known in both, and the changed runs as octree
nodes (their bounding box, a picture, a point cloud). A sharded map is compared part by part:
each part with the other map's leaves in the same partition, so memory is bounded by a part
(and the other map, when it is one file).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from voxtool.errors import ParameterError
from voxtool.kernels import diff as K
from voxtool.keys import keys_to_coords, leaf_span
from voxtool.maps.base import Leaves, join_leaves

STATES = ("unknown", "free", "occupied")
CHANGES = {3 * a + b: f"{STATES[a]}_to_{STATES[b]}" for a in range(3) for b in range(3) if a != b}
# the picture's categories, drawn in this order (the last wins a pixel): name, kinds, colour
PICTURE_KINDS = [
    ("free <-> unknown", (3 * K.FREE + K.UNKNOWN, 3 * K.UNKNOWN + K.FREE), (0.95, 0.75, 0.20)),
    ("no longer occupied", (3 * K.OCCUPIED + K.FREE, 3 * K.OCCUPIED + K.UNKNOWN), (0.15, 0.35, 0.85)),
    ("newly occupied", (3 * K.FREE + K.OCCUPIED, 3 * K.UNKNOWN + K.OCCUPIED), (0.85, 0.10, 0.10)),
]


@dataclass
class MapDiff:
    """What differs between map A and map B, accumulated region by region."""

    resolution: float
    counts: np.ndarray = field(default_factory=lambda: np.zeros(10, dtype=np.int64))
    kl_divergence: float = 0.0
    common_known: int = 0
    blocks: list = field(default_factory=list)  # Leaves of changed nodes, values = change kind
    b_map: object = None  # map B as opened (the picture's background)
    state_maps: list = field(default_factory=list)  # the maps that hold states only (decoded packet logs)
    _changed: Leaves | None = None  # the blocks joined (changed()), until the next add

    def add(self, a: Leaves, a_threshold: float, b: Leaves, b_threshold: float) -> None:
        args = (a.codes, a.depths, a.values, np.float32(a_threshold), b.codes, b.depths, b.values,
                np.float32(b_threshold))
        room = max(1 << 16, (len(a) + len(b)) // 8)  # runs: a guess; rarely too few
        while True:  # room for the changed runs; once more with enough if there were more
            counts = np.zeros_like(self.counts)
            starts, ends, kinds = np.empty(room, np.int64), np.empty(room, np.int64), np.empty(room, np.int64)
            n, kl, common = K.compare_runs(*args, counts, starts, ends, kinds)
            if n <= room:
                break
            room = n
        self.counts += counts
        self._changed = None
        self.kl_divergence += kl
        self.common_known += int(common)
        if n:
            none = np.zeros(0, np.int64)
            m = K.run_blocks(starts[:n], ends[:n], kinds[:n], none, np.zeros(0, np.uint8), none, False)
            codes, depths, bk = np.empty(m, np.int64), np.empty(m, np.uint8), np.empty(m, np.int64)
            K.run_blocks(starts[:n], ends[:n], kinds[:n], codes, depths, bk, True)
            self.blocks.append(Leaves(codes, depths, bk.astype(np.float32)))

    def changed(self) -> Leaves:
        """Every changed node (code, depth, kind as value), in Morton order (joined once: the
        bounding box, the picture and the point cloud all read it)."""
        if self._changed is None:
            self._changed = join_leaves(self.blocks) if self.blocks else \
                Leaves(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.float32))
        return self._changed

    @property
    def changed_voxels(self) -> int:
        return int(sum(self.counts[k] for k in CHANGES))

    def bbox(self) -> dict | None:
        """Outer corners (metres) of every changed voxel, as stats' occupied_bbox."""
        from voxtool.io.picture import key_bounds

        bounds = key_bounds(self.changed())
        if bounds is None:
            return None
        low = keys_to_coords(bounds[0], self.resolution) - self.resolution / 2
        high = keys_to_coords(bounds[1], self.resolution) + self.resolution / 2
        return {"min": [round(float(v), 9) for v in low], "max": [round(float(v), 9) for v in high]}

    def to_dict(self) -> dict:
        c = self.counts
        return {
            "resolution": self.resolution,
            "changed_voxels": self.changed_voxels,
            "changes": {name: int(c[k]) for k, name in CHANGES.items()},
            "unchanged": {"occupied": int(c[3 * K.OCCUPIED + K.OCCUPIED]), "free": int(c[3 * K.FREE + K.FREE])},
            "same_state_other_log_odds": int(c[K.SAME_STATE_NEW_VALUE]),
            "common_known_voxels": self.common_known,
            "kl_divergence": self.kl_divergence,
            "state_maps": self.state_maps,
            "changed_bbox": self.bbox(),
        }


# -- reading two maps region by region -----------------------------------------------------------
@dataclass
class _Map:
    path: Path
    resolution: float
    manifest: dict | None = None  # a sharded map's
    leaves: Leaves | None = None  # a single file's
    threshold: float = 0.0
    origin: list | None = None  # the local origin it was built about (--origin), None: none
    # decoded or merged from a packet log: it holds states, each at one log-odds, not probabilities
    state_map: bool = False


def _open(path: str | os.PathLike) -> _Map:
    from voxtool.io import sharded

    path = Path(path)
    if path.is_dir():
        manifest = sharded.read_manifest(path)
        return _Map(path, float(manifest["map_params"]["resolution"]), manifest=manifest,
                    origin=manifest.get("info", {}).get("origin"))
    from voxtool.api import load_leaves

    leaves, resolution, threshold, meta = load_leaves(path)
    info = meta.get("info", {})
    return _Map(path, resolution, leaves=leaves, threshold=threshold, origin=info.get("origin"),
                state_map="packets" in info)


def split_to_depth(leaves: Leaves, depth: int) -> Leaves:
    """The same voxels with no leaf coarser than `depth` (a coarser leaf becomes its nodes at
    `depth`, in Morton order): every leaf then lies in one shard of that depth."""
    coarse = leaves.depths < depth
    if not coarse.any():
        return leaves
    pieces = np.where(coarse, np.int64(1) << (3 * (depth - leaves.depths.astype(np.int64))), 1)
    first = np.repeat(leaves.codes, pieces)
    step = np.repeat(np.where(coarse, np.int64(1) << np.int64(3 * (16 - depth)), 0), pieces)
    index = np.arange(first.shape[0], dtype=np.int64) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    return Leaves(first + index * step, np.repeat(np.where(coarse, np.uint8(depth), leaves.depths), pieces),
                  np.repeat(leaves.values, pieces))


def _select(leaves: Leaves, mask: np.ndarray) -> Leaves:
    return Leaves(leaves.codes[mask], leaves.depths[mask], leaves.values[mask])


def _regions(a: _Map, b: _Map, progress) -> Iterator[tuple[Leaves, float, Leaves, float]]:
    """(A's leaves, A's threshold, B's leaves, B's threshold) over regions that together cover
    both maps once: the whole maps, or a sharded map's partitions."""
    from voxtool.distbuild import partition_of
    from voxtool.io import sharded
    from voxtool.progress import track

    if a.manifest is None and b.manifest is None:
        yield a.leaves, a.threshold, b.leaves, b.threshold
        return
    lead, other, swapped = (a, b, False) if a.manifest is not None else (b, a, True)
    depth, parts = int(lead.manifest["shard_depth"]), int(lead.manifest["partitions"])
    same_cut = other.manifest is not None and (int(other.manifest["shard_depth"]), int(other.manifest["partitions"])) \
        == (depth, parts)
    if other.manifest is None:
        pieces = split_to_depth(other.leaves, depth)
        partition = partition_of(pieces.codes, depth, parts)
    other_parts = sharded.iter_part_leaves(other.path) if same_cut else None
    # the manifest lists the parts in partition order (formats/sharded.md)
    for p, (_, mine, my_threshold) in enumerate(track(sharded.iter_part_leaves(lead.path), parts, "diff",
                                                      progress, "part")):
        if other.manifest is None:
            theirs, threshold = _select(pieces, partition == p), other.threshold
        elif same_cut:
            _, theirs, threshold = next(other_parts)
        else:  # another cut: gather the voxels of partition p from every part of the other map
            chunks, threshold = [], 0.0
            for _, part, part_threshold in sharded.iter_part_leaves(other.path, check_hash=p == 0):
                threshold = part_threshold
                split = split_to_depth(part, depth)
                chunks.append(_select(split, partition_of(split.codes, depth, parts) == p))
            theirs = join_leaves(chunks)
        here = (mine, my_threshold)
        there = (theirs, threshold)
        yield (*there, *here) if swapped else (*here, *there)


def diff_maps(a_path: str | os.PathLike, b_path: str | os.PathLike, progress: bool | None = False) -> MapDiff:
    """Compare map A with map B (.vxm, .bt or sharded directories of one resolution)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:  # decompressing and checking release the GIL: both at once
        a, b = pool.map(_open, (a_path, b_path))
    if not np.isclose(a.resolution, b.resolution, rtol=0, atol=1e-9):
        raise ParameterError(f"{b.path}: resolution {b.resolution:g} m, {a.path} has {a.resolution:g} m: maps of "
                             "different resolutions are not compared voxel by voxel")
    origins = [np.zeros(3) if m.origin is None else np.asarray(m.origin, dtype=np.float64) for m in (a, b)]
    if not np.allclose(origins[0], origins[1], rtol=0, atol=1e-6):
        raise ParameterError(f"{b.path}: built about the local origin {origins[1].tolist()}, {a.path} about "
                             f"{origins[0].tolist()}: build both with the same --origin X,Y,Z to compare them")
    result = MapDiff(a.resolution, b_map=b, state_maps=[str(m.path) for m in (a, b) if m.state_map])
    for la, ta, lb, tb in _regions(a, b, progress):
        result.add(la, ta, lb, tb)
    return result


# -- outputs ---------------------------------------------------------------------------------
def write_changed_cloud(path: Path, result: MapDiff) -> dict:
    """The changed voxels as a coloured .ply / .pcd point cloud (voxel centres; colours as the
    picture's legend)."""
    from voxtool.atomic import atomic_writer
    from voxtool.io.export import CLOUD_FORMATS, voxel_centres

    fmt = path.suffix.lower().lstrip(".")
    if fmt not in CLOUD_FORMATS:
        raise ParameterError(f"{path}: changed voxels are written as .ply or .pcd")
    changed = result.changed()
    pts = voxel_centres(changed, np.ones(len(changed), dtype=bool), result.resolution)
    kinds = np.repeat(changed.values.astype(np.int64), leaf_span(changed.depths))
    colors = np.zeros((pts.shape[0], 3), dtype=np.uint8)
    for _, members, rgb in PICTURE_KINDS:
        colors[np.isin(kinds, members)] = np.round(np.array(rgb) * 255).astype(np.uint8)
    header, rows = CLOUD_FORMATS[fmt]
    with atomic_writer(path) as handle:
        handle.write(header(len(pts), True))
        handle.write(rows(pts, colors))
    return {"format": fmt, "points": int(pts.shape[0])}


def write_diff_png(path: Path, result: MapDiff, view: str = "top", label: str = "", crop: tuple | None = None) -> dict:
    """A picture of where the maps differ, over map B drawn in grey (export .png's conventions:
    view, axes in metres, scale bar, caption), with a legend of the change kinds; `crop` (xmin,
    ymin, zmin, xmax, ymax, zmax, metres): only the voxels whose centres lie in that box, as
    `export --crop` (the counts in the legend too)."""
    from voxtool.io.picture import write_overlay_png

    changed = result.changed()
    background = _background(result.b_map)
    if crop is not None:
        from voxtool.api import crop_keys
        from voxtool.maps.tree import crop as crop_leaves

        box = crop_keys(crop, result.resolution)
        changed = crop_leaves(changed, *box)
        background = ((crop_leaves(leaves, *box), threshold) for leaves, threshold in background)
    if len(changed) == 0:
        where = "" if crop is None else f" in --crop {','.join(f'{v:g}' for v in crop)}"
        raise ParameterError(f"{path}: the maps do not differ{where}: there is nothing to draw")
    layers = []
    for name, members, rgb in PICTURE_KINDS:
        pick = np.isin(changed.values.astype(np.int64), members)
        picked = Leaves(changed.codes[pick], changed.depths[pick], np.ones(int(pick.sum()), np.float32))
        count = int(result.counts[list(members)].sum()) if crop is None else int(leaf_span(picked.depths).sum())
        layers.append((name, picked, rgb, count))
    return write_overlay_png(path, background, layers, result.resolution, view,
                             label or f"changes from A to B, over B ({result.b_map.path.name})", "B")


def _background(m: _Map) -> Iterator[tuple[Leaves, float]]:
    """A map's leaves: a single file's as read, a sharded map's part by part."""
    from voxtool.io import sharded

    if m.manifest is None:
        yield m.leaves, m.threshold
        return
    for _, leaves, threshold in sharded.iter_part_leaves(m.path, check_hash=False):
        yield leaves, threshold
