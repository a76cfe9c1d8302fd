"""`voxtool view`: look at a map in an Open3D window, or render the view to a PNG."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors, stdout_to_stderr


@click.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--free", "show_free", is_flag=True, help="Start with free space shown (key F toggles it).")
@click.option("--slice", "slice_z", type=float, metavar="Z",
              help="Start with only the occupied voxels of the layer holding height Z (m) (keys S, [ and ]).")
@click.option("--screenshot", type=click.Path(path_type=Path), metavar="OUT.png",
              help="Render the view off-screen to a PNG (with a colour bar in metres) and exit: no window.")
@click.option("--size", default="1280x960", show_default=True, metavar="WxH", help="Rendered size of --screenshot.")
@click.option("--resolution", type=click.FloatRange(min=0.001), default=None, metavar="M",
              help="A point cloud (.pcd/.ply) is shown as the voxels its points fall in, this large (default 0.1 m).")
@click.option("--json", "as_json", is_flag=True, help="With --screenshot: print what was drawn as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (sharded maps).")
@handle_errors
def view(map_file, show_free, slice_z, screenshot, size, resolution, as_json, progress):
    """Show a map (.vxm, OctoMap .bt, or a sharded map directory) or a point cloud (.pcd, .ply:
    `clean`'s outputs, as voxels of --resolution) in a 3D window: occupied voxels
    coloured by height, free space on key F (as coarser cells), a height slice on keys S, [ and ].
    The colour range and the keys are in the window title. A window needs a display; --screenshot
    needs only an OpenGL context (EGL, or xvfb-run)."""
    from voxtool.errors import ParameterError
    from voxtool.viewer import layer_of, load_scene, show
    from voxtool.viewer import screenshot as shoot

    try:
        width, height = (int(v) for v in size.lower().split("x"))
        if not (16 <= width <= 8192 and 16 <= height <= 8192):
            raise ValueError
    except ValueError:
        raise ParameterError(f"--size {size}: use WIDTHxHEIGHT, 16..8192 pixels each") from None
    if screenshot is not None:
        from voxtool.plots import check_png

        check_png(screenshot, "--screenshot")
    scene = load_scene(map_file, progress, resolution)
    layer = layer_of(scene, slice_z)
    if screenshot is None:
        show(scene, map_file.name, show_free, layer)
        return
    with stdout_to_stderr():  # Open3D's C++ prints its notes on stdout; stdout is for the result (--json)
        result = shoot(scene, screenshot, map_file.name, show_free, layer, width, height)
    emit(result, as_json, [(k.replace("_", " "), f"{v:,}" if isinstance(v, int) else str(v))
                           for k, v in result.items()])
