"""`voxtool view`: a map in an Open3D window, or rendered off-screen to a PNG (`--screenshot`).

Occupied voxels are drawn at the map's resolution (pruned leaves expanded), coloured by height
with the same colour map as `export map.png`. Free space would be millions of voxels, so it is
drawn as one point per coarser cell (points, so the occupied voxels stay visible): the finest
power-of-two multiple of the resolution that keeps it under MAX_FREE_CELLS (a cell is drawn when
any free voxel lies in it). A height slice shows the
occupied voxels of one voxel layer. The legacy Open3D window has no text overlay: the legend
(colour range in metres, keys) is its title, and state changes are printed on stderr.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxtool.errors import ParameterError, VoxtoolError
from voxtool.io.picture import COLORMAP, height_colours, slice_layer
from voxtool.keys import TREE_MAX_VAL, expand_leaves, keys_to_coords, leaf_edge, morton_decode

MAX_FREE_CELLS = 1_000_000
FREE_DRAWN = (0.45, 0.75, 0.45)  # free cell centres: darker than the pictures' free colour, as points are thin
BACKGROUND = (1.0, 1.0, 1.0)
KEYS = "F free on/off, S slice on/off, [ and ] slice down/up"


@dataclass
class Scene:
    """What the viewer draws: occupied voxel keys, free cells, and the map's resolution."""

    resolution: float
    occupied: np.ndarray  # (N, 3) int64 keys of occupied voxels
    free_leaves: list  # (first keys, edges in voxels) of the free leaves, per leaf set
    max_free: int = MAX_FREE_CELLS
    _free: tuple | None = None

    @property
    def free(self) -> np.ndarray:
        """(M, 3) int64 keys of free cells, in units of 2^free_shift voxels (computed when first shown)."""
        if self._free is None:
            self._free = _free_cells(self.free_leaves, self.max_free)
        return self._free[0]

    @property
    def free_shift(self) -> int:
        self.free  # noqa: B018 (computes the cells)
        return self._free[1]

    @property
    def height_range(self) -> tuple[float, float]:
        z = keys_to_coords(self.occupied[:, 2], self.resolution)
        return float(z.min()), float(z.max())

    def occupied_layer(self, layer: int | None) -> np.ndarray:
        return self.occupied if layer is None else self.occupied[self.occupied[:, 2] == layer]

    def free_layer(self, layer: int | None) -> np.ndarray:
        """The free cells drawn (those holding the layer's height when sliced)."""
        return self.free if layer is None else self.free[self.free[:, 2] == layer >> self.free_shift]


def _free_cells(parts: list[tuple[np.ndarray, np.ndarray]], max_cells: int) -> tuple[np.ndarray, int]:
    """Unique free cells at the finest shift that keeps them under max_cells; `parts` are
    (first keys, edges in voxels) of free leaves."""
    def packed(keys: np.ndarray) -> np.ndarray:  # keys < 2^16: one int64 per cell, so unique is a 1-D sort
        return (keys[:, 0] << 32) | (keys[:, 1] << 16) | keys[:, 2]

    leaves = sum(len(edge) for _, edge in parts)
    volume = sum(int(np.sum(edge**3)) for _, edge in parts)  # free voxels
    for shift in range(17):
        if volume >> (3 * shift) > max_cells:
            continue  # a cell holds at most 8^shift voxels: too many cells for sure
        expanded = sum(int(np.sum(np.maximum(edge >> shift, 1) ** 3)) for _, edge in parts)
        if expanded - leaves > 8 * max_cells:
            continue  # large leaves alone hold far more cells than can be shown: not worth expanding
        cells = []
        for lo, edge in parts:
            n = np.maximum(edge >> shift, 1)
            for size in np.unique(n):  # a leaf of n^3 cells: its corner cell plus offsets
                sel = n == size
                offsets = np.stack(np.meshgrid(*[np.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3)
                cells.append(packed(((lo[sel] >> shift)[:, None, :] + offsets[None]).reshape(-1, 3)))
        unique = np.unique(np.concatenate(cells)) if cells else np.zeros(0, np.int64)
        if len(unique) <= max_cells:
            return np.stack([unique >> 32, (unique >> 16) & 0xFFFF, unique & 0xFFFF], axis=1), shift
    return np.zeros((0, 3), np.int64), 16


def scene_of(leaf_sets, resolution: float, max_free: int = MAX_FREE_CELLS) -> Scene:
    """The scene of a map given as (leaves, occupancy threshold in log-odds) sets: one for a
    snapshot, one per part of a sharded map (taken one at a time: only what is drawn is kept)."""
    occupied, free = [], []
    for leaves, threshold_log in leaf_sets:
        occ = leaves.values > np.float32(threshold_log)
        occupied.append(morton_decode(expand_leaves(leaves.codes[occ], leaves.depths[occ])).astype(np.int64))
        free.append((morton_decode(leaves.codes[~occ]).astype(np.int64), leaf_edge(leaves.depths[~occ]).astype(np.int64)))
    keys = np.concatenate(occupied) if occupied else np.zeros((0, 3), np.int64)
    if len(keys) == 0:
        raise ParameterError("the map has no occupied voxels: there is nothing to view")
    return Scene(resolution, keys, free, max_free)


CLOUD_RESOLUTION = 0.1  # m: the voxels a point cloud is shown as, unless the viewer is told


def cloud_scene(path: Path, resolution: float | None = None) -> Scene:
    """A point cloud (.pcd with its VIEWPOINT applied, .ply as it is: `clean`'s outputs, an
    export's voxel centres) shown as the voxels of `resolution` its points fall in. A cloud far
    from its frame's origin (a UTM export) is shown about its middle in x and y."""
    from voxtool.keys import KEY_LIMIT

    resolution = resolution or CLOUD_RESOLUTION
    if path.suffix.lower() == ".pcd":
        from voxtool.sources import open_source

        points = np.concatenate([s.points for s in open_source(path).scans]).astype(np.float64)
    else:
        from voxtool.sources.ply import read_ply

        points = np.asarray(read_ply(path), dtype=np.float64)
        points = points[np.isfinite(points).all(axis=1)]
    if points.shape[0] == 0:
        raise ParameterError(f"{path}: the cloud holds no point: there is nothing to view")
    keys = np.floor(points / resolution).astype(np.int64) + TREE_MAX_VAL
    middle = np.zeros(3, np.int64)
    middle[:2] = np.round(np.median(keys[:, :2], axis=0)).astype(np.int64) - TREE_MAX_VAL
    keys -= middle
    if keys.min() < 0 or keys.max() >= KEY_LIMIT:
        raise ParameterError(f"{path}: the cloud spans more than {KEY_LIMIT} voxels of {resolution:g} m: "
                             "view it with a coarser --resolution")
    return Scene(resolution, np.unique(keys, axis=0), [])


def load_scene(path: str | Path, progress: bool | None = False, resolution: float | None = None) -> Scene:
    """A snapshot (.vxm), an OctoMap .bt, a sharded map (read part by part) or a point cloud
    (.pcd, .ply: cloud_scene, at `resolution`)."""
    path = Path(path)
    if path.suffix.lower() in (".pcd", ".ply") and not path.is_dir():
        return cloud_scene(path, resolution)
    if path.is_dir():
        from voxtool.io import sharded
        from voxtool.progress import track

        manifest = sharded.read_manifest(path)
        parts = track(sharded.iter_parts(path), len(manifest["parts"]), "view", progress, "part")
        return scene_of(((backend.leaves(), backend.sensor.threshold_log) for _, backend in parts),
                        manifest["map_params"]["resolution"])
    from voxtool.api import load_leaves

    leaves, resolution, threshold, _ = load_leaves(path)
    return scene_of([(leaves, threshold)], resolution)


def geometries(scene: Scene, show_free: bool, layer: int | None) -> list:
    """The Open3D geometries of a view: occupied voxels (of one layer when sliced), free cells."""
    import open3d as o3d

    res = scene.resolution
    keys = scene.occupied_layer(layer)
    out = []
    if len(keys):
        centres = keys_to_coords(keys, res)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centres))
        cloud.colors = o3d.utility.Vector3dVector(height_colours(centres[:, 2], scene.height_range))
        half = np.full(3, res / 2)
        out.append(o3d.geometry.VoxelGrid.create_from_point_cloud_within_bounds(
            cloud, res, centres.min(axis=0) - half, centres.max(axis=0) + half))
    if show_free and len(scene.free):
        size = res * (1 << scene.free_shift)
        cells = scene.free_layer(layer)
        corners = (cells << scene.free_shift) - TREE_MAX_VAL
        centres = corners * res + size / 2
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centres))
        cloud.paint_uniform_color(FREE_DRAWN)
        out.append(cloud)  # points, not cubes: solid free cells would hide every occupied voxel
    return out


def legend(scene: Scene, name: str) -> str:
    lo, hi = scene.height_range
    return (f"voxtool view {name} - colour: height {lo:.1f} m (dark blue) .. {hi:.1f} m (yellow); "
            f"{len(scene.occupied):,} occupied voxels of {scene.resolution:g} m; keys: {KEYS}")


def _style(vis) -> None:
    option = vis.get_render_option()
    option.background_color = np.array(BACKGROUND)
    option.point_size = 2.0


def _camera(vis, scene: Scene) -> None:
    """An oblique view from the south-west, above the map, z up, framing the central 96 % of the
    occupied voxels (a LiDAR map's few far returns would otherwise shrink it to a speck)."""
    control = vis.get_view_control()
    centres = keys_to_coords(scene.occupied, scene.resolution)
    core = np.percentile(centres, [2, 98], axis=0)
    whole = centres.max(axis=0) - centres.min(axis=0)
    control.set_lookat(np.median(centres, axis=0))
    control.set_front([-0.55, -0.65, 0.52])
    control.set_up([0.0, 0.0, 1.0])
    control.set_zoom(float(np.clip(0.8 * (core[1] - core[0]).max() / max(whole.max(), 1e-9), 0.02, 0.6)))


@contextmanager
def native_stderr_held():
    """The C libraries' own lines on stderr (GLFW, Mesa's "XDG_RUNTIME_DIR is invalid", Open3D's
    INFO) held back while OpenGL starts and renders: shown only when the rendering fails. They
    write to file descriptor 2 directly, so sys.stderr cannot catch them."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        except BaseException:
            os.dup2(saved, 2)
            held.seek(0)
            sys.stderr.write(held.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def render(scene: Scene, show_free: bool, layer: int | None, width: int, height: int) -> np.ndarray:
    """The view rendered off-screen: (height, width, 3) floats in 0..1."""
    import open3d as o3d

    with native_stderr_held():
        vis = o3d.visualization.Visualizer()
        if not vis.create_window(visible=False, width=width, height=height):
            raise VoxtoolError("cannot create an off-screen OpenGL context (Open3D needs EGL or a display: "
                               "try xvfb-run, and Debian's libgl1 libgl1-mesa-dri)")
        try:
            _style(vis)
            for geometry in geometries(scene, show_free, layer):
                vis.add_geometry(geometry)
            _camera(vis, scene)
            vis.poll_events()
            vis.update_renderer()
            return np.asarray(vis.capture_screen_float_buffer(do_render=True))
        finally:
            vis.destroy_window()


def has_display() -> bool:
    """Whether a window can be shown: an X or Wayland display (elsewhere than Linux: assumed).
    Without one Open3D falls back to an invisible EGL window that nobody can close."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def screenshot(scene: Scene, path: Path, name: str, show_free: bool = False, layer: int | None = None,
               width: int = 1280, height: int = 960) -> dict:
    """Write the rendered view with its legend (a colour bar in metres) and caption as a PNG."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    from voxtool.io.picture import save

    image = render(scene, show_free, layer, width, height)
    fig = Figure(figsize=(width / 100 + 1.6, height / 100 + 0.6), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    ax.imshow(image)
    ax.set_axis_off()
    lo, hi = scene.height_range
    fig.colorbar(ScalarMappable(Normalize(lo, hi), colormaps[COLORMAP]), ax=ax, shrink=0.7, label="height (m)")
    shown = len(scene.occupied_layer(layer))
    what = f"{shown:,} occupied voxels" + ("" if layer is None else
                                           f" in the layer z = {keys_to_coords(np.array([layer]), scene.resolution)[0]:.2f} m")
    if show_free:
        ax.legend(handles=[Patch(facecolor=FREE_DRAWN, edgecolor="0.5",
                                 label=f"free (a point per {scene.resolution * (1 << scene.free_shift):g} m cell)")],
                  loc="upper right", fontsize=9)
    ax.set_title(f"{name} · {what} of {scene.resolution:g} m · view from the south-west, z up", loc="left",
                 fontsize=10)
    w, h = save(fig, path)
    background = np.all(np.abs(image - np.array(BACKGROUND)) < 1e-3, axis=2)
    return {"screenshot": str(path), "width": w, "height": h, "occupied_voxels_shown": shown,
            "free_cells_shown": len(scene.free_layer(layer)) if show_free else 0,
            "rendered_pixels": int((~background).sum())}


def show(scene: Scene, name: str, show_free: bool = False, layer: int | None = None) -> None:
    """An interactive window; keys toggle free space and move a height slice."""
    import open3d as o3d

    if not has_display():
        raise VoxtoolError("no display to open a window on ($DISPLAY is not set): render a picture with "
                           "--screenshot OUT.png, or run under xvfb-run")
    state = {"free": show_free, "layer": layer, "shown": []}
    z_keys = np.unique(scene.occupied[:, 2])
    vis = o3d.visualization.VisualizerWithKeyCallback()
    if not vis.create_window(window_name=legend(scene, name), width=1280, height=960):
        raise VoxtoolError("cannot open a window (no display?): use --screenshot PATH, or run under xvfb-run")
    _style(vis)

    def draw(first: bool = False) -> None:
        for geometry in state["shown"]:
            vis.remove_geometry(geometry, reset_bounding_box=False)
        state["shown"] = geometries(scene, state["free"], state["layer"])
        for geometry in state["shown"]:
            vis.add_geometry(geometry, reset_bounding_box=first)

    def say() -> None:
        where = "all heights" if state["layer"] is None else \
            f"slice z = {keys_to_coords(np.array([state['layer']]), scene.resolution)[0]:.2f} m"
        print(f"voxtool view: {where}, free {'on' if state['free'] else 'off'}", file=sys.stderr)

    def redraw() -> None:
        draw()
        say()

    def toggle_free(_vis) -> bool:
        state["free"] = not state["free"]
        redraw()
        return True

    def toggle_slice(_vis) -> bool:
        state["layer"] = None if state["layer"] is not None else int(z_keys[len(z_keys) // 2])
        redraw()
        return True

    def move(step: int):
        def callback(_vis) -> bool:
            if state["layer"] is None:
                state["layer"] = int(z_keys[len(z_keys) // 2])
            i = int(np.clip(np.searchsorted(z_keys, state["layer"]) + step, 0, len(z_keys) - 1))
            state["layer"] = int(z_keys[i])
            redraw()
            return True
        return callback

    vis.register_key_callback(ord("F"), toggle_free)
    vis.register_key_callback(ord("S"), toggle_slice)
    vis.register_key_callback(ord("["), move(-1))
    vis.register_key_callback(ord("]"), move(1))
    draw(first=True)
    _camera(vis, scene)
    # the first line once the window is set up: a Ctrl-C that came while Open3D converted the
    # camera's arguments surfaced as its TypeError (exit 1), not as KeyboardInterrupt (130)
    say()
    try:
        # Open3D's run() holds the interpreter until the window closes, so Ctrl-C did nothing;
        # this loop returns to Python every frame, where KeyboardInterrupt ends it
        while vis.poll_events():
            vis.update_renderer()
            time.sleep(1 / 60)
    finally:
        vis.destroy_window()


def layer_of(scene: Scene, slice_z: float | None) -> int | None:
    return None if slice_z is None else slice_layer(slice_z, scene.resolution)
