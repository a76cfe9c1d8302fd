"""What the commands share: error handling, output, and the option groups."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
from pathlib import Path

import click

from voxtool.errors import VoxtoolError, VoxtoolWarning

SAMPLE_DIR = Path(__file__).resolve().parents[1] / "data" / "sample"
# voxtool.maps.BACKENDS imports the compiled kernels; the CLI keeps its names here so that
# `--help` stays instant (tests/test_cli.py checks the two agree)
BACKEND_NAMES = ("hashmap", "octocache", "octree", "tiny")


def handle_errors(func):
    """Turn VoxtoolError into one line on stderr and its exit code; Ctrl-C into exit 130."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        import warnings

        shown = warnings.showwarning

        def show(message, category, *rest, **kw):  # the library's warnings as voxtool's one-line form
            if issubclass(category, VoxtoolWarning):
                click.echo(f"voxtool: warning: {message}", err=True)
            else:
                shown(message, category, *rest, **kw)

        warnings.showwarning = show
        try:
            from voxtool.jit import start

            start()  # every command runs compiled kernels
            return func(*args, **kwargs)
        except VoxtoolError as err:
            click.echo(f"voxtool: error: {err}", err=True)
            sys.exit(err.exit_code)
        except KeyboardInterrupt:
            click.echo("voxtool: interrupted; no output written", err=True)
            sys.exit(130)
        except MemoryError:
            click.echo("voxtool: error: out of memory", err=True)
            sys.exit(1)
        finally:
            warnings.showwarning = shown

    return wrapper


def emit(data: dict, as_json: bool, rows: list[tuple[str, str]], written=None) -> None:
    """A command's result: JSON on stdout, or aligned rows; `written` (a path or paths) is
    confirmed the same way by every command ("written" in both)."""
    if written is not None:
        paths = [str(p) for p in (written if isinstance(written, list | tuple) else [written])]
        data = {**data, "written": paths if isinstance(written, list | tuple) else paths[0]}
        rows = rows + [("written", p) for p in paths]
    if as_json:
        click.echo(json.dumps(data, indent=2, sort_keys=True))
    else:
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            click.echo(f"{key:<{width}}  {value}")


def warn_dropped(where, figures: dict) -> None:
    """One warning line on stderr for every kind of update a map dropped: never silent."""
    from voxtool.api import dropped_warnings

    for line in dropped_warnings(where, figures):
        click.echo(f"voxtool: warning: {line}", err=True)


def plot_option(what: str):
    """--plot OUT.png: a picture of what the command measured (voxtool.plots)."""
    return click.option("--plot", type=click.Path(path_type=Path), metavar="OUT.png",
                        help=f"Also draw {what} as a PNG (headless matplotlib, written atomically).")


def check_plot(plot) -> None:
    """Refuse a --plot that cannot be written before the work starts, not after it."""
    if plot is not None:
        from voxtool.plots import check_png

        check_png(plot, "--plot")


def view_options(func):
    """--view OUT.mcap / --view-period / --view-keyframe: the replay of decode and merge
    (voxtool.codec.replay)."""
    func = click.option("--view-keyframe", default=10.0, show_default=True, type=click.FloatRange(min=0.0),
                        help="--view: a keyframe (the whole map, so a viewer that seeks shows all of it) at least this "
                             "many seconds of packet time after the last one (0: every message).")(func)
    func = click.option("--view-period", default=1.0, show_default=True, type=click.FloatRange(min=0.0),
                        help="--view: at least this many seconds of packet time between SceneUpdates (0: one per "
                             "distinct packet time).")(func)
    return click.option("--view", type=click.Path(path_type=Path), metavar="OUT.mcap",
                        help="Also write the map as it grew, for Foxglove (and rosbags): ROS 2 foxglove_msgs/SceneUpdate "
                             "messages over packet time, each robot's voxels in its own colour (docs/viewing.md).")(func)


def replay_for(view, period: float, keyframe: float = 10.0):
    """The replay `--view OUT.mcap` writes (None without it), refused early if it cannot be written."""
    if view is None:
        return None
    from voxtool.atomic import check_writable
    from voxtool.codec.replay import Replay
    from voxtool.errors import ParameterError

    if view.suffix.lower() != ".mcap":
        raise ParameterError(f"--view {view}: written as .mcap")
    check_writable(view)
    return Replay(view, period, keyframe)


def cluster_options(func):
    """--workers / --scheduler: run on Dask (voxtool.cluster); neither: no Dask at all."""
    func = click.option("--scheduler", metavar="ADDRESS",
                        help="Run on an existing Dask cluster (e.g. tcp://10.0.0.5:8786); workers read sources by path, "
                             "so they must see the same file system.")(func)
    return click.option("--workers", type=int, default=None,
                        help="Run on a local Dask cluster of N worker processes, started for this command.")(func)


def fleet_rows(report: dict, value) -> list[tuple[str, str]]:
    """A fleet's rows as printed: per source its figure (value(result)) or its error, then totals."""
    rows = []
    for r in report["rows"]:
        where = r["source"] + (f" -> {r['output']}" if r.get("output") else "")
        rows.append((where, value(r["result"]) if r["exit_code"] == 0 else f"FAILED (exit {r['exit_code']}): {r['error']}"))
    t = report["totals"]
    rows.append(("total", f"{t['ok']} of {t['sources']} sources ok in {t['wall_s']:.1f} s"))
    return rows


def emit_fleet(report: dict, as_json: bool, value) -> None:
    """Print a fleet's report, its dropped-data warnings, and exit with the first failure's code."""
    from voxtool.fleet import first_failure

    for r in report["rows"]:
        for line in r.get("warnings", []):
            click.echo(f"voxtool: warning: {line}", err=True)
    written = [r["output"] for r in report["rows"] if r.get("output")]
    emit(report, as_json, fleet_rows(report, value), written=written or None)
    err = first_failure(report)
    if err is not None:
        raise err


def dropped_text(counts: dict) -> str:
    """'N dropped: n1 why1, n2 why2' of a command's drop counts (Scan.drop_counts' keys)."""
    from voxtool.sources.scan import DROP_REASONS

    why = [f"{counts[k]:,} {what}" for k, what in DROP_REASONS.items() if counts.get(k)]
    return f"{counts.get('points_dropped', 0):,} dropped" + (f": {', '.join(why)}" if why else "")


def summary_rows(stats: dict) -> list[tuple[str, str]]:
    """A map's statistics as `build`, `stats` and `decode` print them (docs/parameters.md)."""
    bbox = stats.get("occupied_bbox")
    rows = [
        ("backend", str(stats.get("backend"))),
        ("resolution", f"{stats.get('resolution')} m"),
        ("occupied voxels", f"{stats['occupied_voxels']:,}"),
        ("free voxels", f"{stats['free_voxels']:,}"),
        ("nodes (leaf/inner)", f"{stats['bt_leaf_nodes']:,} / {stats['bt_inner_nodes']:,} in the .bt (max-likelihood) tree"
         if stats.get("bt_leaf_nodes") is not None else "not counted part by part (the tree spans the parts)"),
    ]
    if stats.get("logodds_leaf_nodes") is not None:
        rows.append(("", f"{stats['logodds_leaf_nodes']:,} / {stats['logodds_inner_nodes']:,} in the log-odds octree"))
    if stats.get("pool_bytes") is not None:
        rows.append(("memory", f"{stats['pool_bytes_used'] / 2**20:.1f} MiB in use, {stats['pool_bytes'] / 2**20:.1f} MiB "
                               f"allocated ({stats.get('backend')})"))
    rows.append(("occupied bbox", f"{bbox['min']} .. {bbox['max']}" if bbox else "(empty)"))
    if any(stats.get("origin") or ()):
        rows.append(("local origin", f"{stats['origin']} in the scans' frame (the bbox and a .bt are relative to it; "
                                     ".ply/.pcd/.mcap/.pgm exports are in the scans' frame)"))
    if "scans" in stats:
        dropped = dropped_text(stats)
        if stats.get("no_returns"):
            dropped += f"; {stats['no_returns']:,} no-return beams cleared free space only"
        rows += [("scans", f"{stats['scans']:,}"), ("points", f"{stats['points']:,} ({dropped})")]
        if stats.get("scans_unposed"):
            rows.append(("scans left out", f"{stats['scans_unposed']:,} with no pose at their time (before the first "
                                           "transform or pose, or after the last)"))
    if "workers" in stats:
        rows.append(("dask", f"{stats['workers']} workers, {stats['partitions']} partitions, {stats['batches']} batches "
                             f"of scans: {stats['timings_s']['total']:.3f} s (ray casting summed over tasks "
                             f"{stats['timings_s']['raycast_task_sum']:.3f} s)"))
    elif "timings_s" in stats:
        t = stats["timings_s"]
        lat = stats["scan_latency_ms"]
        threads = f" on {stats['threads']} thread{'s' if stats.get('threads', 1) > 1 else ''}" if "threads" in stats else ""
        rows += [
            ("time", f"{t['total']:.3f} s for the scans{threads} ({t['jit']:.3f} s before: loading the kernels)"),
            ("time per phase", f"read {t['read']:.3f} s, ray casting {t['raycast']:.3f} s, map update {t['update']:.3f} s "
                               "(summed over scans; the phases overlap, so they add up to more)"),
            ("scan latency", f"p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms, max {lat['max']:.1f} ms"),
        ]
    return rows


@contextlib.contextmanager
def stdout_to_stderr():
    """What a library writes to file descriptor 1 (C++ code printing, not Python's sys.stdout)
    goes to stderr meanwhile: a command's stdout holds its result alone (--json that is JSON)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def parse_box(text: str | None, option: str, frame: str = "") -> tuple[float, ...] | None:
    """OPTION XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX as six numbers (metres); None when not given."""
    from voxtool.errors import ParameterError

    if text is None:
        return None
    try:
        box = tuple(float(v) for v in text.split(","))
    except ValueError:
        box = ()
    if len(box) != 6:
        raise ParameterError(f"{option} {text}: give six numbers xmin,ymin,zmin,xmax,ymax,zmax (metres{' ' + frame if frame else ''})")
    return box


def parse_kitti_tr(text: str | None) -> tuple[float, ...] | None:
    """--kitti-tr: 12 numbers, or a calib.txt holding a Tr line; None when not given."""
    from voxtool.errors import ParameterError
    from voxtool.sources.kitti import read_tr, tr_matrix

    if text is None:
        return None
    if Path(text).is_file():
        return tuple(read_tr(Path(text))[:3].ravel())
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) != 12:
        raise ParameterError(f"--kitti-tr {text}: give 12 numbers (row-major 3x4 [R|t]) or a calib.txt with a Tr line")
    return tuple(tr_matrix(values, "--kitti-tr")[:3].ravel())


def ego_box_option():
    return click.option("--ego-box", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                        help="Drop the points inside this box of the sensor's frame (metres): the vehicle's own body, "
                             "whose returns would leave a trail of obstacles along the path. Counted apart "
                             "(points_dropped_ego_box in --json).")


def _source_option_list() -> list:
    """How a source is read: poses, frames, topics, the scan slice, the near-range cut."""
    return [
        click.option("--min-range", default=0.0, show_default=True, type=float, help="Drop points closer than this to the sensor."),
        ego_box_option(),
        click.option("--kitti-tr", metavar="TR", help="A KITTI sequence's Tr (LiDAR to camera) where its calib.txt has "
                     "none: 12 numbers (row-major 3x4 [R|t], commas or spaces) or a calib.txt that has a Tr line."),
        click.option("--poses", type=click.Path(path_type=Path), help="Pose file (TUM, index+TUM or KITTI), one row per scan file, or per scan message of a ROS log "
                     "(instead of its /tf; `voxtool odometry` writes one)."),
        click.option("--no-viewpoint", is_flag=True,
                     help="PCD points are already in the world frame; take only the ray origin from VIEWPOINT/--poses."),
        click.option("--topic", help="MCAP/bag PointCloud2, LaserScan or VelodyneScan topic (default: the only one)."),
        click.option("--world-frame", default=None, help="MCAP/bag /tf frame the map is built in (default: the root of the /tf tree above the cloud's frame)."),
        click.option("--pose-topic", help="MCAP/bag Odometry/PoseStamped topic giving the sensor pose (instead of /tf)."),
        click.option("--bad-scans", type=click.Choice(["fail", "skip"]), default="fail", show_default=True,
                     help="A scan that cannot be read (a truncated file, a corrupt message): fail stops with its error; "
                          "skip warns on one line per scan, counts it (scans_skipped in --json) and goes on."),
        click.option("--start", default=0, show_default=True, type=int, help="First scan index to use."),
        click.option("--stop", default=None, type=int, help="Stop before this scan index."),
        click.option("--every", default=1, show_default=True, type=int, help="Use every n-th scan."),
    ]


def _apply_options(func, options: list):
    for option in reversed(options):
        func = option(func)
    return func


def scan_options(func):
    """Options shared by every command that reads scans: source interpretation and map model."""
    options = [
        click.option("--resolution", default=0.2, show_default=True, type=float, help="Voxel edge length in metres."),
        click.option("--max-range", default=-1.0, show_default=True, type=float,
                     help="Rays longer than this are cut here and mark no hit (OctoMap maxrange); < 0 = unlimited."),
        click.option("--merge-rays", is_flag=True,
                     help="Integrate rays with identical voxel paths once (TinyOctoMap); the map is unchanged under OctoMap's model."),
        *_source_option_list(),
        click.option("--prob-hit", default=0.7, show_default=True, type=float, help="Occupancy probability of a hit (OctoMap)."),
        click.option("--prob-miss", default=0.4, show_default=True, type=float, help="Occupancy probability of a pass-through."),
        click.option("--clamp-min", default=0.1192, show_default=True, type=float, help="Lower probability clamp."),
        click.option("--clamp-max", default=0.971, show_default=True, type=float, help="Upper probability clamp."),
        click.option("--threshold", default=0.5, show_default=True, type=float, help="Occupancy probability threshold."),
    ]
    return _apply_options(func, options)


def source_options(func):
    """The options of scan_options that say how a source is read (no map model)."""
    return _apply_options(func, _source_option_list())


def source_setup(kw: dict):
    """SourceOptions from the source_options values (removed from kw)."""
    from voxtool.sources import SourceOptions

    poses = kw.pop("poses")
    options = SourceOptions(poses=str(poses) if poses else None, no_viewpoint=kw.pop("no_viewpoint"),
                            topic=kw.pop("topic"), world_frame=kw.pop("world_frame"), pose_topic=kw.pop("pose_topic"),
                            start=kw.pop("start"), stop=kw.pop("stop"), every=kw.pop("every"),
                            min_range=kw.pop("min_range"), bad_scans=kw.pop("bad_scans"),
                            ego_box=parse_box(kw.pop("ego_box"), "--ego-box", "in the sensor's frame"),
                            kitti_tr=parse_kitti_tr(kw.pop("kitti_tr")))
    return with_origin(options, kw.pop("origin", None))  # commands with origin_option among their **kw


def scan_setup(kw: dict):
    """(SourceOptions, MapParams, SensorModel) from the scan_options values (removed from kw)."""
    from voxtool.config import MapParams, SensorModel

    min_range = kw["min_range"]
    options = source_setup(kw)
    params = MapParams(resolution=kw.pop("resolution"), max_range=kw.pop("max_range"), min_range=min_range,
                       merge_rays=kw.pop("merge_rays"))
    sensor = SensorModel(kw.pop("prob_hit"), kw.pop("prob_miss"), kw.pop("clamp_min"), kw.pop("clamp_max"),
                         kw.pop("threshold"))
    return options, params, sensor


origin_option = click.option(
    "--origin", metavar="auto|X,Y,Z",
    help="Build about a local origin (metres in the scans' frame, snapped to the voxel grid): scans in a city or UTM "
         "frame, km from its origin, fit the octree's key range (+-3276.8 m at 0.1 m). auto: the first scan's sensor "
         "position. Outputs of points (.ply/.pcd/.mcap) are written back in the scans' frame (float64 where float32 "
         "would blur a voxel); a .bt is in the local frame; `stats` reports the origin.")


def with_origin(options, text: str | None):
    """SourceOptions with the --origin given (auto or X,Y,Z), resolved when the source is read."""
    from dataclasses import replace

    from voxtool.sources import parse_origin

    return replace(options, origin=parse_origin(text)) if text is not None else options


threads_option = click.option(
    "--threads", default=0, show_default=True, type=click.IntRange(min=0),
    help="Threads for ray casting and map updates; 0: the cores this process may use.")


def backend_options(func):
    """Options that choose and configure the map backend (build, encode)."""
    options = [
        click.option("--backend", type=click.Choice(BACKEND_NAMES), default="octree", show_default=True,
                     help="Map backend (docs/backends.md)."),
        click.option("--param", "backend_params", multiple=True, metavar="KEY=VALUE",
                     help="Backend option, e.g. shard_depth=10 (octree); tau=4, buckets=65536, overlap=1, order=morton (octocache); "
                          "pool_blocks=4096, map_size=40 (tiny); n_lim=50000, d_inf=0.2, inf_range=8, d_in=30, ttl=5, "
                          "p_init=0.5, discretize=1 (hashmap)."),
        click.option("--pool-blocks", type=int,
                     help="tiny: a fixed memory budget in blocks of 8 nodes (<= 4096: 16-bit nodes, the paper's 64 KiB); "
                          "updates it cannot hold are dropped (with a warning). Default: the pool grows as the map needs."),
        click.option("--map-size", type=float, help="tiny: edge of the cubic map extent in metres (sets the depth)."),
        click.option("--schedule", multiple=True, metavar="SCAN:KEY=VALUE",
                     help="hashmap: change p_init, n_lim, d_in, d_inf, inf_range or ttl from scan SCAN on (repeatable)."),
        threads_option,
    ]
    for option in reversed(options):
        func = option(func)
    return func


def backend_setup(kw: dict) -> tuple[str, dict]:
    """(backend name, its options) from the backend_options values (removed from kw)."""
    extra = parse_params(kw.pop("backend_params"))
    pool_blocks, map_size, schedule = kw.pop("pool_blocks"), kw.pop("map_size"), kw.pop("schedule")
    if pool_blocks is not None:
        extra["pool_blocks"] = pool_blocks
    if map_size is not None:
        extra["map_size"] = map_size
    if schedule:
        extra["schedule"] = parse_schedule(schedule)
    extra["threads"] = kw.pop("threads")
    return kw.pop("backend"), extra


def resolve_source(source, sample):
    from voxtool.errors import ParameterError

    if sample == (source is not None):
        raise ParameterError("give exactly one of SOURCE or --sample")
    return SAMPLE_DIR if sample else source


def parse_params(items) -> dict:
    """KEY=VALUE strings to a dict of int / float / str values."""
    from voxtool.errors import ParameterError

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ParameterError(f"--param '{item}' must read KEY=VALUE")
        for cast in (int, float):
            try:
                out[key] = cast(value)
                break
            except ValueError:
                continue
        else:
            out[key] = value
    return out


def parse_schedule(items) -> list:
    """'SCAN:KEY=VALUE' strings to (scan index, key, value) triples."""
    from voxtool.errors import ParameterError

    out = []
    for item in items:
        at, _, rest = item.partition(":")
        key, _, value = rest.partition("=")
        try:
            out.append((int(at), key, float(value)))
        except ValueError:
            raise ParameterError(f"--schedule '{item}' must read SCAN:KEY=VALUE") from None
    return out


def int_list(text: str) -> list:
    return [int(v) for v in text.split(",")] if text else []
