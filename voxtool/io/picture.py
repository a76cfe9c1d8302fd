"""Pictures of a map a person can read (`export map.png`): a top, front or side view, or one
height slice, drawn with matplotlib (headless: a Figure on the Agg canvas, no pyplot), with a
colour bar in metres, a legend for free and unknown space, a scale bar, axes in metres, the
axis arrows and a caption (source, view, resolution, metres per pixel).

A view projects the map along one axis: a pixel is occupied when any voxel on its line is,
coloured by the coordinate of the nearest occupied voxel seen from the viewer (the top view:
the height of the highest one); else free when any voxel on it is free; else unknown. A slice
shows the one voxel layer that holds height Z, seen from above.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxtool.errors import ParameterError
from voxtool.keys import TREE_MAX_VAL, keys_to_coords, leaf_edge, morton_decode
from voxtool.maps.base import Leaves

# view: (image's horizontal axis, vertical axis, axis looked along, the viewer on its + side)
VIEWS = {"top": (0, 1, 2, True), "front": (0, 2, 1, False), "side": (1, 2, 0, True)}
AXIS = "xyz"
UNKNOWN, FREE, OCCUPIED = 0, 1, 2
FREE_RGB = (0.80, 0.90, 0.80)
UNKNOWN_RGB = (0.93, 0.93, 0.93)
SLICE_RGB = (0.80, 0.15, 0.10)
COLORMAP = "viridis"
NO_GROUND_RGB = (0.55, 0.55, 0.55)  # an occupied pixel coloured by height above a ground that is not known
MAX_SIDE = 1600  # raster pixels on the longer side: 2^k voxels per pixel above that


def height_colours(z: np.ndarray, z_range: tuple[float, float] | None = None) -> np.ndarray:
    """RGB in 0..1 of heights on COLORMAP, over `z_range` (default: the heights' own range); the
    one height colouring of pictures, the viewer and the Foxglove scene."""
    from matplotlib import colormaps

    lo, hi = z_range if z_range is not None else ((float(z.min()), float(z.max())) if z.size else (0.0, 1.0))
    return colormaps[COLORMAP]((z - lo) / max(hi - lo, 1e-9))[:, :3]


def _extent(leaves: Leaves) -> tuple[np.ndarray, np.ndarray]:
    """First and last key (per axis) of every leaf."""
    lo = morton_decode(leaves.codes).astype(np.int64)
    return lo, lo + leaf_edge(leaves.depths)[:, None].astype(np.int64) - 1


def slice_layer(z: float, resolution: float) -> int:
    key = int(np.floor(z / resolution)) + TREE_MAX_VAL
    if not 0 <= key < 2 * TREE_MAX_VAL:
        raise ParameterError(f"--slice {z:g}: outside the map's key range at resolution {resolution:g} m")
    return key


@dataclass
class Raster:
    """The picture's pixels, filled leaf set by leaf set (a sharded map part by part)."""

    view: str
    kmin: np.ndarray  # first key on the horizontal and vertical axes
    shift: int  # a pixel is 2^shift voxels on a side
    width: int
    height: int
    layer: int | None = None  # the z key of a slice

    @classmethod
    def covering(cls, view: str, kmin, kmax, layer: int | None = None, max_side: int = MAX_SIDE) -> Raster:
        u, w, _, _ = VIEWS[view]
        lo = np.array([kmin[u], kmin[w]], np.int64)
        size = np.array([kmax[u], kmax[w]], np.int64) - lo + 1
        shift = 0
        while int(size.max()) > max_side << shift:
            shift += 1
        raster = cls(view, lo, shift, int((size[0] - 1) >> shift) + 1, int((size[1] - 1) >> shift) + 1, layer)
        raster.state = np.zeros(raster.width * raster.height, np.int8)
        raster.depth = np.full(raster.width * raster.height, -np.inf)  # nearest occupied, signed
        return raster

    def add(self, leaves: Leaves, threshold_log: float) -> None:
        from voxtool.kernels.raster import fill_leaves

        u, w, a, from_plus = VIEWS[self.view]
        fill_leaves(self.state, self.depth, self.width, int(self.kmin[0]), int(self.kmin[1]), self.shift, u, w, a,
                    from_plus, -1 if self.layer is None else int(self.layer), leaves.codes, leaves.depths,
                    leaves.values, np.float32(threshold_log))

    def values_m(self, resolution: float) -> np.ndarray:
        """The colour coordinate of occupied pixels in metres (NaN elsewhere), rows from the bottom:
        with a ground (`above_ground`), the top's height above the ground under the pixel's
        centre column (NaN where that ground is unknown)."""
        _, _, _, from_plus = VIEWS[self.view]
        key = np.where(self.state == OCCUPIED, self.depth if from_plus else -self.depth, np.nan)
        values = keys_to_coords(key, resolution).reshape(self.height, self.width)
        ground = getattr(self, "ground", None)
        if ground is None:
            return values
        half = (1 << self.shift) // 2  # the pixel's centre column
        kx = self.kmin[0] + (np.arange(self.width) << self.shift) + half
        ky = self.kmin[1] + (np.arange(self.height) << self.shift) + half
        return values - ground.under(*np.meshgrid(kx, ky))  # rows from the bottom, as values

    def metres(self, resolution: float) -> tuple[float, float, float, float]:
        """Extent (left, right, bottom, top) of the picture in metres (voxel edges)."""
        lo = (self.kmin - TREE_MAX_VAL) * resolution
        step = resolution * (1 << self.shift)
        return float(lo[0]), float(lo[0] + self.width * step), float(lo[1]), float(lo[1] + self.height * step)


def key_bounds(leaves: Leaves) -> tuple[np.ndarray, np.ndarray] | None:
    if len(leaves) == 0:
        return None
    lo, hi = _extent(leaves)
    return lo.min(axis=0), hi.max(axis=0)


def _nice_length(span_m: float) -> float:
    """A scale bar length near a fifth of the picture: 1, 2 or 5 times a power of ten."""
    target = span_m / 5
    power = 10 ** np.floor(np.log10(target))
    return float(max((m * power for m in (1, 2, 5) if m * power <= target), default=power))


def figure(raster: Raster, resolution: float, label: str):
    """The matplotlib Figure of a raster: picture, colour bar, legend, scale bar, arrows, caption."""
    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredDirectionArrows, AnchoredSizeBar

    u, w, a, _ = VIEWS[raster.view]
    state = raster.state.reshape(raster.height, raster.width)
    rgb = np.empty((raster.height, raster.width, 3))
    rgb[:] = UNKNOWN_RGB
    rgb[state == FREE] = FREE_RGB
    occupied = state == OCCUPIED
    values = raster.values_m(resolution)
    norm = None
    one_height = False  # every occupied pixel at one height: one colour, no colour bar
    above = getattr(raster, "ground", None) is not None
    if raster.layer is not None:
        rgb[occupied] = SLICE_RGB
    elif above and occupied.any():
        # height above the ground on the band's scale (clipped); no ground known: the slice grey
        lo, hi = raster.band
        norm = Normalize(lo, hi + 1e-9)
        known = occupied & ~np.isnan(values)
        rgb[known] = colormaps[COLORMAP](norm(np.clip(values[known], lo, hi)))[:, :3]
        raster.colour_range = (lo, hi, float(np.mean((values[known] < lo) | (values[known] > hi))) if known.any() else 0.0)
        rgb[occupied & np.isnan(values)] = NO_GROUND_RGB
    elif occupied.any():
        lo, hi, clipped = colour_range(values[occupied], resolution)
        one_height = hi == lo
        raster.colour_range = None if one_height else (lo, hi, clipped)
        if one_height:  # nothing for a colour bar to scale
            rgb[occupied] = colormaps[COLORMAP](0.5)[:3]
        else:
            norm = Normalize(lo, hi)
            rgb[occupied] = colormaps[COLORMAP](norm(np.clip(values[occupied], lo, hi)))[:, :3]
    left, right, bottom, top = raster.metres(resolution)
    aspect = (top - bottom) / max(right - left, 1e-9)
    flat = aspect < 0.6  # a wide picture: the colour bar goes below it
    tall = float(np.clip(9.5 * aspect, 0.5, 14))  # the picture's height (inches), and its width from that:
    wide = float(np.clip(tall / aspect + (2.5 if norm is not None and not flat else 0.8), 4.0, 11.0))  # none blank
    fig = Figure(figsize=(wide, tall + (2.8 if flat else 1.4)), dpi=150, layout="constrained")
    ax = fig.add_subplot()
    ax.imshow(rgb, origin="lower", extent=(left, right, bottom, top), interpolation="nearest")
    ax.set_xlabel(f"{AXIS[u]} (m)")
    ax.set_ylabel(f"{AXIS[w]} (m)")
    if raster.layer is not None:
        z0 = keys_to_coords(np.array([raster.layer]), resolution)[0] - resolution / 2
        title = f"slice z = {z0:.3g} .. {z0 + resolution:.3g} m"
    else:
        title = f"{raster.view} view (looking along {'-' if VIEWS[raster.view][3] else '+'}{AXIS[a]})"
    ax.set_title(title, loc="left")
    handles = [Patch(facecolor=FREE_RGB, edgecolor="0.5", label="free"),
               Patch(facecolor=UNKNOWN_RGB, edgecolor="0.5", label="unknown")]
    if raster.layer is not None:
        handles.insert(0, Patch(facecolor=SLICE_RGB, label="occupied"))
    if one_height:
        z0 = float(np.nanmin(values[occupied]))
        handles.insert(0, Patch(facecolor=colormaps[COLORMAP](0.5)[:3], label=f"occupied (all at {z0:.3g} m)"))
    # one layout rule for every view: the legend in a row of its own above the picture, never over the title
    fig.legend(handles=handles, loc="outside upper right", ncol=len(handles), fontsize=8, frameon=False)
    if norm is not None:
        from matplotlib.cm import ScalarMappable

        what = "height of the highest occupied voxel" if raster.view == "top" else \
            f"{AXIS[a]} of the nearest occupied voxel"
        if above:
            what = "height of the highest occupied voxel above the ground under it (grey: no ground known)"
        clipped = "" if above or not raster.colour_range[2] else \
            f"; {raster.colour_range[2]:.1%} of the pixels beyond the bar, drawn at its ends"
        fig.colorbar(ScalarMappable(norm, colormaps[COLORMAP]), ax=ax, shrink=0.8, label=f"{what} (m){clipped}",
                     location="bottom" if flat else "right")
    length = _nice_length(right - left)
    ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length:g} m", "lower right", pad=0.5, sep=4,
                                  frameon=True, size_vertical=(top - bottom) / 150))
    # the axes' directions, in the lower left corner (data units: both arrows equally long)
    arrow = min(length / 2, (top - bottom) / 4)
    letters = min(arrow / 3, max(right - left, top - bottom) / 80)  # TextPath: a height in metres
    ax.add_artist(AnchoredDirectionArrows(ax.transData, f"+{AXIS[u]}", f"+{AXIS[w]}", length=arrow,
                                          loc="lower left", fontsize=letters, sep_x=arrow / 10, sep_y=arrow / 10,
                                          back_length=0, color="k", head_width=6, head_length=8, tail_width=1.5))
    step = resolution * (1 << raster.shift)
    # a figure-level x label: the constrained layout keeps room for it below the tick labels
    fig.supxlabel(f"{label} · resolution {resolution:g} m · 1 pixel = {step:g} m · "
                  f"{int(occupied.sum()):,} occupied pixels", fontsize=8, x=0.01, ha="left")
    return fig


def colour_range(values: np.ndarray, resolution: float) -> tuple[float, float, float]:
    """(low, high, share of the values outside) of a picture's colours: the 1st to the 99th
    percentile, so that a return 17 m under the road does not flatten every colour; the whole
    range where that is at most a voxel wider. low == high: every value one height."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if hi - lo < resolution / 2:
        return lo, lo, 0.0
    p1, p99 = (float(v) for v in np.percentile(values, [1, 99]))
    if (hi - lo) - (p99 - p1) <= resolution or p99 - p1 < resolution / 2:
        return lo, hi, 0.0
    return p1, p99, float(np.mean((values < p1) | (values > p99)))


def save(fig, path: Path) -> tuple[int, int]:
    """Write a figure as PNG (atomically), cropped to what is drawn; returns its (width, height) in pixels."""
    import io

    from voxtool.atomic import atomic_writer

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight", pad_inches=0.1)
    blob = buffer.getvalue()
    with atomic_writer(path) as handle:
        handle.write(blob)
    return int.from_bytes(blob[16:20], "big"), int.from_bytes(blob[20:24], "big")  # the IHDR chunk


def check_options(view: str, slice_z: float | None) -> None:
    if view not in VIEWS:
        raise ParameterError(f"--view {view}: use one of {', '.join(VIEWS)}")
    if slice_z is not None and view != "top":
        raise ParameterError("--slice shows one height layer from above: use it with --view top")


def figures(raster: Raster) -> dict:
    drawn = getattr(raster, "colour_range", None)
    return {"format": "png", "view": raster.view, "raster_width": raster.width, "raster_height": raster.height,
            "voxels_per_pixel": 1 << raster.shift, "occupied_pixels": int((raster.state == OCCUPIED).sum()),
            "free_pixels": int((raster.state == FREE).sum()),
            # the colour bar's metres and the share of pixels beyond them; null: no colour bar (one height)
            "colour_range_m": None if drawn is None else [round(drawn[0], 6), round(drawn[1], 6)],
            "colour_clipped_share": None if drawn is None else round(drawn[2], 6)}


def picture(leaves: Leaves, resolution: float, threshold_log: float, view: str = "top",
            slice_z: float | None = None, above_ground: tuple[float, float] | None = None) -> Raster:
    """The raster of a map's leaves; `above_ground` (MIN, MAX metres): a top view coloured by
    height above the ground found in the map (voxtool.ground), on that scale."""
    check_options(view, slice_z)
    if above_ground is not None and (view != "top" or slice_z is not None):
        raise ParameterError("--above-ground colours a top view by height above the ground: not with --view or --slice")
    bounds = key_bounds(leaves)
    if bounds is None:
        raise ParameterError("the map is empty: there is nothing to draw")
    layer = slice_layer(slice_z, resolution) if slice_z is not None else None
    raster = Raster.covering(view, *bounds, layer)
    raster.add(leaves, threshold_log)
    if above_ground is not None:
        from voxtool.ground import MAP_GRID_GROUND, ground_of, occupied_voxels

        keys, hits = occupied_voxels(leaves, threshold_log)
        raster.ground = ground_of(keys, resolution, MAP_GRID_GROUND, weights=hits)
        raster.band = above_ground
    return raster


ROOF_SHARE = 0.5  # a top view whose occupied pixels show a roof this often is drawn below it
ROOF_BAND = 0.2  # of the map's occupied height range: the top band a roof lies in


def roof_height(raster: Raster, resolution: float) -> float | None:
    """The lowest height of a roof or ceiling that hides a top view's floor plan (metres), or
    None (roof_of on the raster's occupied pixels' tops)."""
    tops = raster.values_m(resolution)
    return roof_of(tops[~np.isnan(tops)], resolution / 2)


def roof_of(tops: np.ndarray, half_voxel: float = 0.0) -> float | None:
    """The roof under which a top view shows the floor plan, from what each pixel shows from
    above (`tops`, metres), or None: more than ROOF_SHARE of the pixels show their top within the
    highest ROOF_BAND of the heights, over a range of at least 2 m (a room, a shack, a hall;
    outdoors, trees and buildings cover too little for it)."""
    if tops.size < 100:
        return None
    lo, hi = float(tops.min()), float(tops.max())
    if hi - lo < 2.0:
        return None
    band = tops[tops >= hi - ROOF_BAND * (hi - lo)]
    if band.size < ROOF_SHARE * tops.size:
        return None
    return float(np.percentile(band, 2)) - half_voxel  # the roof's lower edge


def write_png(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
              view: str = "top", slice_z: float | None = None, label: str = "", below_roof: bool = True,
              above_ground: tuple[float, float] | None = None) -> dict:
    """A picture of the map's leaves (write_leaf_sets for one set); `above_ground`: coloured by
    height above the ground (picture())."""
    if above_ground is not None:
        if include_free:
            raise ParameterError(f"{path}: a picture always shows free space (legend: free); --free is for .ply/.pcd")
        raster = picture(leaves, resolution, threshold_log, view, slice_z, above_ground)
        caption = (label or path.stem) + f" · coloured by height above the ground, {above_ground[0]:g} to {above_ground[1]:g} m"
        width, height = save(figure(raster, resolution, caption), path)
        return {**figures(raster), "width": width, "height": height, "caption": caption,
                "above_ground": list(above_ground)}
    return write_leaf_sets(path, lambda: [(leaves, threshold_log)], resolution, include_free, view, slice_z, label,
                           below_roof)


def write_leaf_sets(path: Path, leaf_sets, resolution: float, include_free: bool, view: str = "top",
                    slice_z: float | None = None, label: str = "", below_roof: bool = True, progress=False) -> dict:
    """A picture of a map given as `leaf_sets()`: a fresh iterator of (leaves, threshold log-odds)
    each time it is called (a snapshot's leaves a chunk at a time, a sharded map's parts), read
    once for the bounds and once to draw, so memory is bounded by a set, not the map. A top view
    of a map with a roof (`below_roof`, unless --slice) is drawn below it, so that it shows the
    floor plan, and its caption says so."""
    from voxtool.progress import bar

    if include_free:
        raise ParameterError(f"{path}: a picture always shows free space (legend: free); --free is for .ply/.pcd")
    check_options(view, slice_z)
    with bar(None, "export .png", progress, "pass") as passes:
        lo = hi = None
        for leaves, _ in leaf_sets():
            bounds = key_bounds(leaves)
            if bounds is not None:
                lo = bounds[0] if lo is None else np.minimum(lo, bounds[0])
                hi = bounds[1] if hi is None else np.maximum(hi, bounds[1])
        if lo is None:
            raise ParameterError(f"{path}: the map is empty: there is nothing to draw")
        passes.update(1)
        layer = slice_layer(slice_z, resolution) if slice_z is not None else None

        def draw(keep=None) -> Raster:
            raster = Raster.covering(view, lo, hi, layer)
            for leaves, threshold in leaf_sets():
                raster.add(leaves if keep is None else keep(leaves), threshold)
            passes.update(1)
            return raster

        raster = draw()
        roof = roof_height(raster, resolution) if below_roof and view == "top" and slice_z is None else None
        note = ""
        if roof is not None:
            from voxtool.keys import centre_key_range
            from voxtool.maps.tree import crop

            _, top_key = centre_key_range(0.0, roof, resolution)
            box = (np.zeros(3, np.int64), np.array([65535, 65535, int(top_key)]))
            below = draw(lambda leaves: crop(leaves, *box))
            if (below.state == OCCUPIED).any():
                raster = below
                note = (f" · below the roof at {roof:.2f} m (the floor plan; --crop with another zmax to choose the "
                        "heights, --view side for the walls)")
    caption = (label or path.stem) + note
    width, height = save(figure(raster, resolution, caption), path)
    out = {**figures(raster), "width": width, "height": height, "caption": caption}
    if note:
        out["below_roof_m"] = round(roof, 6)
    return out


def picture_of_parts(path: Path, output: Path, include_free: bool, progress=False, view: str = "top",
                     slice_z: float | None = None, label: str = "") -> dict:
    """write_png for a sharded map, part by part (memory: its largest part)."""
    from voxtool.io import sharded

    manifest = sharded.read_manifest(path)
    checked = []  # the parts' hashes are checked on the first pass only

    def parts():  # each part's stored leaves, without rebuilding its tree
        for _, leaves, threshold in sharded.iter_part_leaves(path, check_hash=not checked):
            yield leaves, threshold
        checked.append(True)

    return write_leaf_sets(output, parts, manifest["map_params"]["resolution"], include_free, view, slice_z,
                           label or path.name, progress=progress)


BACKGROUND_OCCUPIED_RGB = (0.55, 0.55, 0.55)


def write_overlay_png(path: Path, background, layers: list, resolution: float, view: str = "top", label: str = "",
                      background_name: str = "map") -> dict:
    """Coloured voxels over a map drawn in grey (export .png's conventions: view, axes in metres,
    scale bar, caption), framed on the coloured voxels, with a legend. `background`: the map's
    (leaves, threshold) part by part; `layers`: (name, leaves, rgb, count) drawn in order (the
    last wins a pixel), or (name, leaves, rgb, count, legend) where the legend text is not
    "name (count voxels)"."""
    from matplotlib.patches import Patch

    check_options(view, None)
    spans = [b for b in (key_bounds(layer[1]) for layer in layers) if b is not None]
    if not spans:
        raise ParameterError(f"{path}: nothing to draw")
    bounds = (np.min([b[0] for b in spans], axis=0), np.max([b[1] for b in spans], axis=0))
    margin = max(8, int((bounds[1] - bounds[0]).max() // 10))
    kmin, kmax = bounds[0] - margin, bounds[1] + margin
    base = Raster.covering(view, kmin, kmax)
    for leaves, threshold in background:
        base.add(leaves, threshold)
    masks = []
    for name, leaves, rgb, count, *legend in layers:
        raster = Raster.covering(view, kmin, kmax)
        raster.add(Leaves(leaves.codes, leaves.depths, np.ones(len(leaves), np.float32)), 0.0)
        masks.append((name, raster.state == OCCUPIED, rgb, count, legend[0] if legend else f"{name} ({count:,} voxels)"))
    fig = figure(base, resolution, label)
    ax = fig.axes[0]
    state = base.state.reshape(base.height, base.width)
    pixels = np.empty((base.height, base.width, 3))
    pixels[:] = UNKNOWN_RGB
    pixels[state == FREE] = FREE_RGB
    pixels[state == OCCUPIED] = BACKGROUND_OCCUPIED_RGB
    for _, mask, rgb, _, _ in masks:
        pixels[mask.reshape(base.height, base.width)] = rgb
    ax.images[0].set_data(pixels)
    for extra in fig.axes[1:]:  # the height colour bar belongs to the plain map's picture
        extra.remove()
    handles = [Patch(facecolor=rgb, edgecolor="0.5", label=legend) for _, _, rgb, _, legend in masks]
    handles += [Patch(facecolor=BACKGROUND_OCCUPIED_RGB, edgecolor="0.5", label=f"{background_name} occupied"),
                Patch(facecolor=FREE_RGB, edgecolor="0.5", label=f"{background_name} free"),
                Patch(facecolor=UNKNOWN_RGB, edgecolor="0.5", label="unknown")]
    ax.legend(handles=handles, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3, fontsize=8, frameon=False)
    width, height = save(fig, path)
    return {"format": "png", "view": view, "width": width, "height": height,
            "changed_pixels": int(sum(m[1].sum() for m in masks)),
            "voxels": {name: count for name, _, _, count, _ in masks},
            "legend": [legend for *_, legend in masks],
            "background_known_pixels": int(((base.state == FREE) | (base.state == OCCUPIED)).sum())}
