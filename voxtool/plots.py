"""Plots of what a command measured (`--plot out.png`), drawn headless (matplotlib's Agg canvas,
no pyplot) and written atomically like every output:

- `stats LOG.mcap --plot`: bandwidth over time per robot (bytes in each 1 s window, with the
  log's average as a dashed line) and the size of every packet;
- `cache-bench --plot`: where each configuration's time goes (the OctoCache paper's decomposition:
  ray casting, cache insert, eviction, octree update on the calling thread, final flush) and its
  cache hit ratio;
- `build --plot`: each scan's latency (ray casting + map update) and the map's size after it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.io.picture import save

NS = 1_000_000_000
COLOURS = "tab10"


def _figure(rows: int, height: float = 3.2):
    from matplotlib.figure import Figure

    return Figure(figsize=(10, height * rows), dpi=120, layout="constrained")


def series_colour(i: int) -> tuple[float, float, float]:
    """The i-th series' colour (RGB, 0..1): plots and the replay's robots share it."""
    from matplotlib import colormaps

    return tuple(float(c) for c in colormaps[COLOURS](i % 10)[:3])


def log_figure(stats: dict, series: dict[str, tuple[np.ndarray, np.ndarray]]):
    """Bandwidth per robot in 1 s windows (aligned to the log's first packet, as `stats` counts
    them per robot from its own first packet) and packet sizes, over seconds since the first packet."""
    fig = _figure(2)
    bw, sizes = fig.subplots(2, 1, sharex=True)
    firsts = {robot: int(s.min()) for robot, (s, _) in series.items()}
    t0 = min(firsts.values())
    apart_days = (max(firsts.values()) - t0) / NS / 86400
    end = 0.0
    for i, (robot, (stamps, nbytes)) in enumerate(sorted(series.items())):
        row = stats["robots"][robot]
        first = int(stamps.min())
        if apart_days > 1:  # clocks a day or more apart: each robot from its own first packet
            t0 = first
        per_second = np.bincount((stamps - first) // NS, weights=nbytes)
        start = (first - t0) / NS + np.arange(len(per_second))
        edges = np.append(start, start[-1] + 1)
        colour = series_colour(i)
        bw.stairs(per_second / 1e3, edges, color=colour, linewidth=1.5,
                  label=f"{robot}: avg {row['avg_Bps'] / 1e3:,.1f} kB/s, 1 s max {row['max_Bps'] / 1e3:,.1f} kB/s")
        bw.axhline(row["avg_Bps"] / 1e3, color=colour, linestyle="--", linewidth=1)
        sizes.scatter((stamps - t0) / NS, nbytes, s=8, color=colour, label=f"{robot}: {len(nbytes):,} packets")
        end = max(end, float(edges[-1]))
    bw.set_ylabel("bandwidth (kB/s, 1 s windows)")
    bw.set_ylim(bottom=0)
    bw.legend(fontsize=8, loc="upper right")
    bw.set_title(f"{Path(stats['log']).name}: {stats['packets']:,} packets, {stats['bytes']:,} bytes "
                 "(dashed: average over the log)", loc="left", fontsize=10)
    sizes.set_yscale("log")
    sizes.set_ylabel("packet size (bytes)")
    sizes.set_xlabel("time since the first packet (s)" if apart_days <= 1 else
                     f"time since each robot's first packet (s): their clocks are {apart_days:,.0f} days apart")
    sizes.set_xlim(0, end)
    sizes.legend(fontsize=8, loc="upper right")
    return fig


# a configuration's time, in the order the paper stacks it; the row keys that hold each part
PARTS = (("ray casting", "raycast_s"), ("cache insert", "insert_s"), ("eviction", "evict_s"),
         ("octree update (calling thread)", "thread1_update_s"), ("final flush", "flush_s"))


def _label(row: dict) -> str:
    if row["backend"] == "octree":
        return "octree"
    return f"cache ovl{row['overlap']} tau{row['tau']} b{row['buckets']} {row['order']}"


def cache_figure(result: dict):
    """Stacked time per configuration (plain octree: ray casting + octree update) and hit ratio."""
    rows = result["rows"]
    labels = [_label(r) for r in rows]
    fig = _figure(2, height=max(2.2, 0.45 * len(rows) + 1.2))
    times, hits = fig.subplots(1, 2, width_ratios=(3, 1), sharey=True)
    y = np.arange(len(rows))
    left = np.zeros(len(rows))
    for i, (name, key) in enumerate(PARTS):
        part = np.array([r.get("octree_update_s" if r["backend"] == "octree" and key == "thread1_update_s" else key, 0.0)
                         or 0.0 for r in rows])
        times.barh(y, part, left=left, color=series_colour(i), label=name)
        left += part
    times.scatter([r["total_s"] for r in rows], y, marker="|", s=300, color="k", label="measured total", zorder=3)
    times.set_yticks(y, labels, fontsize=8)
    times.invert_yaxis()
    times.set_xlabel("time (s)")
    from voxtool.sources import source_names

    times.set_title(f"{source_names([result['source']])[0]} at {result['resolution']:g} m: where the time goes", loc="left",
                    fontsize=10)
    fig.legend(*times.get_legend_handles_labels(), loc="outside lower center", ncol=6, fontsize=8)
    ratio = np.array([r.get("hit_ratio", np.nan) for r in rows], float)
    hits.barh(y, np.nan_to_num(ratio) * 100, color=series_colour(5))
    for yi, value in zip(y, ratio):
        hits.text(1, yi, "no cache" if np.isnan(value) else f"{value * 100:.1f} %", va="center", fontsize=7)
    hits.set_xlim(0, 100)
    hits.set_xlabel("cache hit ratio (%)")
    return fig


def build_figure(result: dict, label: str):
    """Per-scan latency and the map's used size after each scan, over the scans."""
    scans = result["per_scan"]
    n = np.arange(1, len(scans["latency_ms"]) + 1)
    fig = _figure(2)
    latency, size = fig.subplots(2, 1, sharex=True)
    latency.plot(n, scans["latency_ms"], marker=".", linewidth=1, color=series_colour(0))
    lat = result["scan_latency_ms"]
    latency.axhline(lat["p50"], color="0.4", linestyle="--", linewidth=1, label=f"median {lat['p50']:.1f} ms")
    latency.set_ylabel("scan latency (ms)\nray casting + map update")
    latency.set_ylim(bottom=0)
    latency.legend(fontsize=8)
    latency.set_title(f"{label}: {result['scans']:,} scans, {result['backend']} backend, "
                      f"{result['occupied_voxels']:,} occupied voxels at the end", loc="left", fontsize=10)
    size.plot(n, np.array(scans["map_bytes"]) / 2**20, color=series_colour(1))
    size.set_ylabel("map size (MiB used)")
    size.set_xlabel("scan")
    size.set_xlim(1, max(len(n), 2))
    size.xaxis.get_major_locator().set_params(integer=True)
    size.set_ylim(bottom=0)
    return fig


def check_png(path: Path, option: str) -> None:
    """A PNG output that cannot be written is refused before the work starts, not after it."""
    from voxtool.atomic import check_writable
    from voxtool.errors import ParameterError

    if Path(path).suffix.lower() != ".png":
        raise ParameterError(f"{option} {path}: written as .png")
    check_writable(path)


def write_plot(fig, path: str | Path) -> dict:
    """Write a plot as PNG (atomically); the figures `--json` reports about it."""
    width, height = save(fig, Path(path))
    return {"plot": str(path), "width": width, "height": height}


CLEAN_VIEWS = {"top": (0, 1, 2), "front": (0, 2, 1), "side": (1, 2, 0)}  # (horizontal, vertical, colour) axes


CLEAN_RASTER = 520  # pixels along the longer side of a panel: about its width on the 120-dpi page


PIXEL_CHUNK = 1 << 21  # points placed on the raster at a time


def _nearest_pixels(u: np.ndarray, w: np.ndarray, depth: np.ndarray, extent, shape,
                    among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For points (u, w) over `extent` (u0, u1, w0, w1) in a raster of `shape` (rows, columns):
    each lit pixel (flat index, ascending) and the point it shows, the one of greatest `depth`
    (nearest the viewer; of equal ones the last), as a scatter plot drawn in that order would.
    PIXEL_CHUNK points at a time, in float64, each chunk's winners against the raster's so far:
    18.7 M points at once took 2 GB. `among`: a mask of the points to place (None: all); the
    indices returned are into all the points."""
    rows, cols = shape
    u0, u1, w0, w1 = extent
    best_depth = np.full(rows * cols, -np.inf)
    best = np.full(rows * cols, -1, dtype=np.int64)
    for a in range(0, len(u), PIXEL_CHUNK):
        b = min(a + PIXEL_CHUNK, len(u))
        pick = np.arange(a, b) if among is None else np.flatnonzero(among[a:b]) + a
        uu, ww, dd = (np.asarray(v[pick], dtype=np.float64) for v in (u, w, depth))
        col = np.floor((uu - u0) / max(u1 - u0, 1e-9) * cols).astype(np.int64)
        row = np.floor((ww - w0) / max(w1 - w0, 1e-9) * rows).astype(np.int64)
        inside = np.flatnonzero((col >= 0) & (col < cols) & (row >= 0) & (row < rows))
        pixel = row[inside] * cols + col[inside]
        order = np.lexsort((dd[inside], pixel))  # by pixel, nearest last
        last = np.flatnonzero(np.append(pixel[order][1:] != pixel[order][:-1], True))
        p, i = pixel[order][last], inside[order][last]
        better = dd[i] >= best_depth[p]  # a later chunk's point of equal depth is drawn over
        best_depth[p[better]] = dd[i[better]]
        best[p[better]] = pick[i[better]]
    lit = np.flatnonzero(best >= 0)
    return lit, best[lit]


def clean_figure(points: np.ndarray, dynamic: np.ndarray, title: str, extent_m: float | None = None,
                 view: str = "top", below_roof: bool = True, above_ground: tuple | None = None,
                 resolution: float = 0.1) -> tuple:
    """(figure, roof height or None): `clean` before and after, seen from above (or, as export's pictures, from the front or
    the side): every point by height (depth for front/side, with a colour bar) with the removed
    ones in red, then the static points alone (same axes): side by side, or one above the other
    where the view is wide (a side view). `extent_m`: a square of that side around the points'
    median (a long drive is otherwise too small to judge). A top view of a place with a roof is
    drawn below it, as export's pictures are. The points are drawn as pixels of a raster (the
    nearest point of each): a scatter plot of a million points took 5 s to draw.
    `above_ground` (MIN, MAX metres; a top view): coloured by height above the ground found in
    the static points at `resolution` (voxtool.ground) on that scale, grey where none is known."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from voxtool.io.picture import COLORMAP, NO_GROUND_RGB, height_colours, roof_of

    if above_ground is not None and view != "top":
        from voxtool.errors import ParameterError

        raise ParameterError("--above-ground colours a top view by height above the ground: not with --view")

    u, w, c = CLEAN_VIEWS[view]
    pu, pw, z = points[:, u], points[:, w], points[:, c]  # views: no copy of 18 M points (float64 per chunk)
    static = ~dynamic
    if extent_m is not None and z.size:
        cx, cy = float(np.median(pu)), float(np.median(pw))
        extent = (cx - extent_m / 2, cx + extent_m / 2, cy - extent_m / 2, cy + extent_m / 2)
    elif z.size:
        u0, u1, w0, w1 = float(pu.min()), float(pu.max()), float(pw.min()), float(pw.max())
        extent = (u0, u1 if u1 > u0 else u0 + 1.0, w0, w1 if w1 > w0 else w0 + 1.0)
    else:
        extent = (0.0, 1.0, 0.0, 1.0)
    aspect = (extent[3] - extent[2]) / (extent[1] - extent[0])
    stacked = aspect < 0.6  # a wide view: one panel above the other, each the page's width (twice the pixels)
    scale = CLEAN_RASTER * (2 if stacked else 1) / max(extent[1] - extent[0], extent[3] - extent[2])
    shape = (max(1, int(round((extent[3] - extent[2]) * scale))), max(1, int(round((extent[1] - extent[0]) * scale))))
    roof = None
    if view == "top" and below_roof and z.size:
        # on a coarser raster (about export's voxel pixels): points are sparser than voxels, and
        # on the drawing's raster a roof's returns cover too few of the pixels to be found
        _, shown = _nearest_pixels(pu, pw, z, extent, (max(1, shape[0] // 8), max(1, shape[1] // 8)))
        roof = roof_of(z[shown].astype(np.float64))
    drawn = np.ones(len(z), bool) if roof is None else z < roof
    lo, hi = np.percentile(z[drawn].astype(np.float64), [1, 99]) if drawn.any() else (0.0, 1.0)
    hi = max(hi, lo + 1e-6)
    # coloured are the points drawn, not every point (18 M x 4 float64: 0.6 GB)
    pixel, shown = _nearest_pixels(pu, pw, z, extent, shape, among=static & drawn)
    colours = height_colours(np.clip(z[shown].astype(np.float64), lo, hi), (float(lo), float(hi)))
    if above_ground is not None and z.size:
        above = height_above_ground(points[:, [u, w, c]].astype(np.float64), static, resolution)[shown]
        lo, hi = float(above_ground[0]), max(float(above_ground[1]), float(above_ground[0]) + 1e-6)
        colours = height_colours(np.clip(np.nan_to_num(above, nan=lo), lo, hi), (lo, hi))
        colours[np.isnan(above), :3] = NO_GROUND_RGB
    after_image = np.ones((shape[0] * shape[1], 4))
    after_image[:, 3] = 0.0  # transparent where no point lies
    after_image[pixel, :3] = colours[:, :3]
    after_image[pixel, 3] = 1.0
    before_image = after_image.copy()
    gone = dynamic & drawn
    if gone.any():  # the removed ones in red, over everything, 2 x 2 pixels
        pixel, _ = _nearest_pixels(pu, pw, z, extent, shape, among=gone)
        for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
            r, cl = pixel // shape[1] + dr, pixel % shape[1] + dc
            ok = (r < shape[0]) & (cl < shape[1])
            before_image[r[ok] * shape[1] + cl[ok]] = (1.0, 0.0, 0.0, 1.0)

    if stacked:
        fig = Figure(figsize=(10, float(np.clip(2 * 8.4 * aspect, 1.0, 12)) + 1.5), dpi=120, layout="constrained")
        before, after = fig.subplots(2, 1, sharex=True, sharey=True)
    else:
        fig = Figure(figsize=(10, float(np.clip(4.3 * aspect, 2.5, 9)) + 1.6), dpi=120, layout="constrained")
        before, after = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, name, image in ((before, "before", before_image), (after, "after", after_image)):
        ax.imshow(image.reshape(shape[0], shape[1], 4), origin="lower", extent=extent, interpolation="nearest",
                  aspect="equal")
        ax.set_title(f"{name}: {int(static.sum()):,} static points"
                     + (f", {int(dynamic.sum()):,} removed (red)" if name == "before" else ""), fontsize=9)
        ax.set_ylabel(f"{'xyz'[w]} (m)")
        ax.set_xlabel(f"{'xyz'[u]} (m)")
    if stacked:
        before.set_xlabel("")
    else:
        after.set_ylabel("")
    what = "height" if view == "top" else f"{'xyz'[c]} (depth, nearest point drawn)"
    if above_ground is not None:
        what = "height above the ground (grey: none known)"
    fig.colorbar(ScalarMappable(Normalize(float(lo), float(hi)), colormaps[COLORMAP]), ax=[before, after],
                 shrink=0.8, label=f"{what} (m)", location="bottom" if not stacked else "right")
    note = "" if roof is None else f", below the roof at {roof:.2f} m ({int((~drawn).sum()):,} points above it not drawn)"
    fig.suptitle(f"{title}, {view} view{note}", fontsize=10)
    return fig, roof


def height_above_ground(points: np.ndarray, static: np.ndarray, resolution: float) -> np.ndarray:
    """Each point's height above the ground found in the static points (voxtool.ground, the
    points' voxels at `resolution`); NaN where no ground is known under it."""
    from voxtool.ground import ground_of
    from voxtool.keys import TREE_MAX_VAL

    keys = np.floor(points / resolution).astype(np.int64) + TREE_MAX_VAL
    ground = ground_of(np.unique(keys[static], axis=0), resolution)
    return points[:, 2] - ground.under(keys[:, 0], keys[:, 1])
