"""voxtool command line: a thin layer over the library. Heavy imports stay inside commands."""

from __future__ import annotations

import functools
import json
import os
import sys
from pathlib import Path

# Before numpy loads: voxtool's matrix products are small (a scan's points times a 3x3
# rotation); threaded BLAS only spins on them and takes the cores the ray casting runs on (seen
# in perf as blas_thread_server). A default for the command line only; a user's setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import click  # noqa: E402

from voxtool import __version__  # noqa: E402
from voxtool.errors import VoxtoolError  # noqa: E402

SAMPLE_DIR = Path(__file__).parent / "data" / "sample"
# voxtool.maps.BACKENDS imports the compiled kernels; the CLI keeps its names here so that
# `--help` stays instant (tests/test_cli.py checks the two agree)
BACKEND_NAMES = ("hashmap", "octocache", "octree", "tiny")


def handle_errors(func):
    """Turn VoxtoolError into one line on stderr and its exit code; Ctrl-C into exit 130."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
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

    return wrapper


def emit(data: dict, as_json: bool, rows: list[tuple[str, str]]) -> None:
    if as_json:
        click.echo(json.dumps(data, indent=2, sort_keys=True))
    else:
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            click.echo(f"{key:<{width}}  {value}")


def summary_rows(stats: dict) -> list[tuple[str, str]]:
    bbox = stats.get("occupied_bbox")
    rows = [
        ("backend", str(stats.get("backend"))),
        ("resolution", f"{stats.get('resolution')} m"),
        ("occupied voxels", f"{stats['occupied_voxels']:,}"),
        ("free voxels", f"{stats['free_voxels']:,}"),
        ("nodes (leaf/inner)", f"{stats['leaf_nodes']:,} / {stats['inner_nodes']:,}"),
        ("memory", f"{stats['memory_bytes'] / 2**20:.1f} MiB"),
        ("occupied bbox", f"{bbox['min']} .. {bbox['max']}" if bbox else "(empty)"),
    ]
    if "scans" in stats:
        rows += [("scans", f"{stats['scans']:,}"), ("points", f"{stats['points']:,} ({stats['points_dropped']:,} dropped)")]
    if "timings_s" in stats:
        t = stats["timings_s"]
        lat = stats["scan_latency_ms"]
        rows += [
            ("time total", f"{t['total']:.3f} s (read {t['read']:.3f}, raycast {t['raycast']:.3f}, update {t['update']:.3f})"),
            ("scan latency", f"p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms, max {lat['max']:.1f} ms"),
        ]
    return rows


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="voxtool")
def main() -> None:
    """Turn LiDAR scan streams into 3D occupancy voxel maps, measure and share them.

    Exit codes: 0 ok, 1 error, 2 bad parameter, 3 bad source, 4 point outside the key range,
    5 bad map/packet file, 6 regression found by `stats --compare`, 130 interrupted.
    """


def scan_options(func):
    """Options shared by every command that reads scans: source interpretation and map model."""
    options = [
        click.option("--resolution", default=0.2, show_default=True, type=float, help="Voxel edge length in metres."),
        click.option("--max-range", default=-1.0, show_default=True, type=float,
                     help="Rays longer than this are cut here and mark no hit (OctoMap maxrange); < 0 = unlimited."),
        click.option("--min-range", default=0.0, show_default=True, type=float, help="Drop points closer than this to the sensor."),
        click.option("--merge-rays", is_flag=True,
                     help="Integrate rays with identical voxel paths once (TinyOctoMap); the map is unchanged under OctoMap's model."),
        click.option("--poses", type=click.Path(path_type=Path), help="Pose file (TUM, index+TUM or KITTI), one row per scan file."),
        click.option("--no-viewpoint", is_flag=True,
                     help="PCD points are already in the world frame; take only the ray origin from VIEWPOINT/--poses."),
        click.option("--topic", help="MCAP PointCloud2 topic (default: the only one)."),
        click.option("--world-frame", default=None, help="MCAP /tf frame the map is built in (default: the root of the /tf tree above the cloud's frame)."),
        click.option("--pose-topic", help="MCAP Odometry/PoseStamped topic giving the sensor pose (instead of /tf)."),
        click.option("--start", default=0, show_default=True, type=int, help="First scan index to use."),
        click.option("--stop", default=None, type=int, help="Stop before this scan index."),
        click.option("--every", default=1, show_default=True, type=int, help="Use every n-th scan."),
        click.option("--prob-hit", default=0.7, show_default=True, type=float, help="Occupancy probability of a hit (OctoMap)."),
        click.option("--prob-miss", default=0.4, show_default=True, type=float, help="Occupancy probability of a pass-through."),
        click.option("--clamp-min", default=0.1192, show_default=True, type=float, help="Lower probability clamp."),
        click.option("--clamp-max", default=0.971, show_default=True, type=float, help="Upper probability clamp."),
        click.option("--threshold", default=0.5, show_default=True, type=float, help="Occupancy probability threshold."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def scan_setup(kw: dict):
    """(SourceOptions, MapParams, SensorModel) from the scan_options values (removed from kw)."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.sources import SourceOptions

    poses = kw.pop("poses")
    options = SourceOptions(poses=str(poses) if poses else None, no_viewpoint=kw.pop("no_viewpoint"),
                            topic=kw.pop("topic"), world_frame=kw.pop("world_frame"), pose_topic=kw.pop("pose_topic"),
                            start=kw.pop("start"), stop=kw.pop("stop"), every=kw.pop("every"), min_range=kw["min_range"])
    params = MapParams(resolution=kw.pop("resolution"), max_range=kw.pop("max_range"), min_range=kw.pop("min_range"),
                       merge_rays=kw.pop("merge_rays"))
    sensor = SensorModel(kw.pop("prob_hit"), kw.pop("prob_miss"), kw.pop("clamp_min"), kw.pop("clamp_max"),
                         kw.pop("threshold"))
    return options, params, sensor


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
        click.option("--pool-blocks", type=int, help="tiny: memory budget in blocks of 8 nodes (<= 4096: 16-bit nodes)."),
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


@main.command()
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool (norlab, BSD-3) as SOURCE.")
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the map snapshot (.vxm) here (atomically).")
@backend_options
@scan_options
@click.option("--share", type=click.Path(path_type=Path), help="hashmap: write newly occupied voxels (ring buffer) as a packet log.")
@click.option("--ring", default=3, show_default=True, type=int, help="hashmap --share: frames per broadcast (k).")
@click.option("--json", "as_json", is_flag=True, help="Print statistics and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def build(source, sample, output, share, ring, as_json, progress, **kw):
    """Build an occupancy map from SOURCE: a directory of PCD (or PLY + --poses) scans, a single
    PCD/PLY file, a ROS 2 .mcap file, or an OctoMap .graph file."""
    from voxtool.api import build_map

    options, params, sensor = scan_setup(kw)
    backend, extra = backend_setup(kw)
    result = build_map(resolve_source(source, sample), options, params, sensor, backend, output, progress, extra,
                       share, ring)
    emit(result, as_json, summary_rows(result) + ([("written", str(output))] if output else []))


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


@main.command("cache-bench")
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the shipped sample as SOURCE.")
@scan_options
@click.option("--tau", default="4", show_default=True, help="Bucket threshold(s) after eviction, comma-separated sweep.")
@click.option("--buckets", default="", help="Bucket count(s) (powers of two), comma-separated; default: the paper's rule.")
@click.option("--order", default="morton", show_default=True,
              help="Write-back order(s) of evicted voxels: morton, xyz, random, bucket (comma-separated sweep).")
@click.option("--overlap", default="0,1", show_default=True,
              help="0 (write-back on the calling thread) and/or 1 (on its own thread, the paper's two threads).")
@threads_option
@click.option("--json", "as_json", is_flag=True, help="Print all rows as JSON.")
@handle_errors
def cache_bench_cmd(source, sample, tau, buckets, order, overlap, threads, as_json, **kw):
    """Run the same scans through the plain octree and through OctoCache settings; report time and
    where it goes, cache hit ratio, octree writes saved, memory, and check the maps are identical
    (exit 1 when any differs)."""
    from voxtool.cachebench import cache_bench
    from voxtool.errors import ParameterError, VoxtoolError

    options, params, sensor = scan_setup(kw)
    orders = [o.strip() for o in order.split(",") if o.strip()]
    try:
        taus, bucket_list, overlaps = int_list(tau), int_list(buckets) or [None], int_list(overlap)
    except ValueError:
        raise ParameterError("--tau, --buckets and --overlap take comma-separated integers") from None

    def progress(k, n, backend, cfg):
        click.echo(f"[{k + 1}/{n}] {backend} {cfg}", err=True)

    result = cache_bench(resolve_source(source, sample), options.__dict__, params.to_dict(), sensor.to_dict(),
                         taus, bucket_list, orders, overlaps, threads, progress if sys.stderr.isatty() else None)
    rows = result["rows"]
    if as_json:
        click.echo(json.dumps(result, indent=2))
    else:
        head = f"{'backend':<9} {'ovl':>3} {'tau':>3} {'buckets':>8} {'order':<7} {'total s':>8} {'raycast':>8} {'insert':>7} {'evict':>6} {'octree':>7} {'wait':>6} {'hit %':>6} {'written/updates':>17} {'speedup':>7} {'peak MiB':>8} {'same':>4}"
        click.echo(head)
        for r in rows:
            cache = r["backend"] == "octocache"
            click.echo(
                f"{r['backend']:<9} {r.get('overlap', '-')!s:>3} {r.get('tau', '-')!s:>3} {r.get('buckets', '-')!s:>8} "
                f"{r.get('order', '-'):<7} {r['total_s']:>8.3f} {r['raycast_s']:>8.3f} {r.get('insert_s', 0):>7.3f} "
                f"{r.get('evict_s', 0):>6.3f} {r['octree_update_s']:>7.3f} {r.get('wait_s', 0):>6.3f} "
                f"{(100 * r['hit_ratio'] if cache else 0):>6.1f} "
                f"{(str(r['written_to_octree']) + '/' + str(r['voxel_updates'])) if cache else '-':>17} "
                f"{r['speedup']:>7.2f} {(r['peak_rss_bytes'] or 0) / 2**20:>8.1f} {'yes' if r['identical_to_octree'] else 'NO':>4}")
    bad = [r for r in rows if not r["identical_to_octree"]]
    if bad:
        raise VoxtoolError(f"{source or 'sample'}: {len(bad)} OctoCache configuration(s) built a map different from the octree")


@main.command()
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the shipped sample as SOURCE.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="Packet log to write (.mcap).")
@click.option("--robot", default="r1", show_default=True, help="Robot id (1..16 bytes) stamped on every packet.")
@backend_options
@scan_options
@click.option("--scheme", type=click.Choice(["hilbert", "nested", "racer", "occupied"]), default=None,
              help="What a packet holds (docs/packets.md).  [default: hilbert; nested with --codec cm]")
@click.option("--codec", type=click.Choice(["zstd", "zlib", "cm", "none"]), default="zstd", show_default=True,
              help="Payload compression. cm: a 3D context model with a range coder, 40-60 % smaller than "
                   "zstd; codes boxes in x-y-z order, so only with the nested scheme (docs/packets.md).")
@click.option("--max-changes", default=50_000, show_default=True, type=int, help="Emit a packet once this many voxels changed state (d).")
@click.option("--max-interval", default=0.5, show_default=True, type=float, help="...or this many seconds of scan time passed (t).")
@click.option("--ring", default=3, show_default=True, type=int, help="Frames per packet of the 'occupied' scheme (k).")
@click.option("--keyframe-every", default=0, show_default=True, type=click.IntRange(min=0),
              help="Also emit a full-state keyframe every n packets (0: never).")
@click.option("--rate", "rate_hz", default=10.0, show_default=True, type=float, help="Scan rate (Hz) assumed when the source has no stamps.")
@click.option("--json", "as_json", is_flag=True, help="Print the encoding report as JSON.")
@click.option("--progress/--no-progress", default=None)
@handle_errors
def encode(source, sample, output, robot, scheme, codec, max_changes, max_interval, ring, keyframe_every,
           rate_hz, as_json, progress, **kw):
    """Map SOURCE and write the voxel state changes as packets to an MCAP packet log."""
    from voxtool.codec.encode import EncodeOptions, encode_stream
    from voxtool.errors import ParameterError
    from voxtool.maps import make_backend
    from voxtool.sources import open_source

    if output.suffix.lower() != ".mcap":
        raise ParameterError(f"{output}: packet logs are written as .mcap")
    from voxtool.atomic import check_writable

    check_writable(output)
    options, params, sensor = scan_setup(kw)
    backend, extra = backend_setup(kw)
    src = resolve_source(source, sample)
    if scheme is None:
        scheme = "nested" if codec == "cm" else "hilbert"
    opts = EncodeOptions(robot, scheme, codec, max_changes, max_interval, ring, keyframe_every, rate_hz)
    mapper = make_backend(backend, params, sensor, **extra)
    stream = open_source(src, options)
    info = {"source": str(src), "backend": backend, "backend_params": {k: v for k, v in extra.items() if k != "schedule"},
            "map_params": params.to_dict(), "sensor_model": sensor.to_dict()}
    result = encode_stream(stream, mapper, output, opts, info, progress)
    emit(result, as_json, [(k, str(v)) for k, v in result.items()])


@main.command()
@click.argument("log", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the replayed state map as a snapshot (.vxm).")
@click.option("--json", "as_json", is_flag=True, help="Dump packet headers and decoded voxel states as JSON.")
@click.option("--relay", is_flag=True, help="Integrate 'occupied' frames into a hash map like sensor hits (receiver side).")
@click.option("--d-inf", default=0.2, show_default=True, type=float, help="--relay: inflation radius of the receiving hash map.")
@handle_errors
def decode(log, output, as_json, relay, d_inf):
    """Replay a packet log into a state map (free / occupied / unknown)."""
    from voxtool.codec.fusion import fuse, packets_of, save_state_map

    if relay:
        from voxtool.api import backend_stats
        from voxtool.codec.log import read_log
        from voxtool.codec.share import relay as relay_frames
        from voxtool.config import MapParams, SensorModel
        from voxtool.io.mapfile import save_map
        from voxtool.maps.hashmap import HashVoxelMap

        meta, _ = read_log(log)
        res = next((m.get("resolution") for m in meta.values() if m.get("resolution")), None)
        if res is None:
            from voxtool.errors import FormatError

            raise FormatError(f"{log}: packet log metadata gives no resolution")
        m = HashVoxelMap(MapParams(resolution=res), SensorModel(), d_inf=d_inf)
        frames = relay_frames(log, m)
        result = backend_stats(m)
        result["frames"] = frames
        if output is not None:
            save_map(output, m, {"source": str(log), "relayed_frames": frames})
        emit(result, as_json, summary_rows(result))
        return

    if as_json:
        dump = []
        for p in packets_of(log):
            head = {k: v for k, v in p.__dict__.items() if k not in ("keys", "states")}
            head["voxels"] = [[int(a), int(b), int(c), int(s)] for (a, b, c), s in zip(p.keys, p.states)]
            dump.append(head)
        click.echo(json.dumps(dump))
    result = fuse([log])
    if output is not None:
        save_state_map(output, result, {"source": str(log), "packets": result.packets})
    if not as_json:
        occ = int((result.states == 1).sum())
        emit({}, False, [("packets", str(result.packets)), ("occupied voxels", f"{occ:,}"),
                         ("free voxels", f"{result.states.shape[0] - occ:,}")] + ([("written", str(output))] if output else []))


@main.command()
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the fused state map (.vxm).")
@click.option("--extrinsic", multiple=True, help="ROBOT=tx,ty,tz,qw,qx,qy,qz: pose of that robot's map in the fused frame.")
@click.option("--simulate-loss", type=float, default=None, help="Run the request/response resend simulation with this loss rate.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Seed of the loss simulation.")
@click.option("--json", "as_json", is_flag=True)
@handle_errors
def merge(logs, output, extrinsic, simulate_loss, seed, as_json):
    """Fuse the packet logs of several robots: every voxel takes its latest-stamped state."""
    from voxtool.codec.fusion import Extrinsic, fuse, save_state_map

    ext = dict(Extrinsic.parse(e) for e in extrinsic)
    result = fuse(list(logs), ext)
    occ = int((result.states == 1).sum())
    out = {"packets": result.packets, "occupied_voxels": occ, "free_voxels": int(result.states.shape[0] - occ),
           "robots": result.robots}
    if simulate_loss is not None:
        from voxtool.codec.resend import simulate

        sim = simulate(list(logs), loss=simulate_loss, seed=seed, extrinsics=ext)
        out["simulation"] = sim
    if output is not None:
        save_state_map(output, result, {"sources": [str(p) for p in logs], "packets": result.packets})
    rows = [("packets", str(result.packets)), ("occupied voxels", f"{occ:,}"), ("free voxels", f"{out['free_voxels']:,}")]
    for robot, info in result.robots.items():
        gaps = info["gaps"]
        rows.append((f"robot {robot}", f"{info['packets']} packets, {len(gaps)} missing seq" + (f" {gaps[:10]}" if gaps else "")))
    if "simulation" in out:
        sim = out["simulation"]
        rows.append(("simulation", f"loss {simulate_loss}: sent {sim['sent']}, lost {sim['lost']}, resent {sim['resent']}, "
                                   f"keyframes {sim['keyframes']}, equal to lossless: {sim['equal_to_lossless']}"))
    emit(out, as_json, rows)


@main.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
@click.option("--compare", "baseline", type=click.Path(path_type=Path),
              help="Baseline JSON (from `stats --json`); exit 6 when a figure drifts beyond --tolerance "
                   "(maps: voxel, node, scan and point counts; packet logs: packets, bytes, bandwidth).")
@click.option("--tolerance", default=0.0, show_default=True, type=float, help="Relative tolerance for --compare.")
@handle_errors
def stats(map_file, as_json, baseline, tolerance):
    """Statistics of a map snapshot (.vxm), an OctoMap .bt file, or a packet log (.mcap)."""
    from voxtool.api import map_stats
    from voxtool.stats import LOG_COMPARED, compare

    if map_file.suffix.lower() == ".mcap":
        from voxtool.codec.logstats import log_stats

        result = log_stats(map_file)
        rows = [("packets", str(result["packets"])), ("bytes", f"{result['bytes']:,}"),
                ("total bandwidth", f"avg {result['total']['avg_Bps']:,.0f} B/s, max {result['total']['max_Bps']:,.0f} B/s")]
        for robot, r in result["robots"].items():
            rows.append((f"robot {robot}", f"{r['scheme']}/{r['codec']}: avg {r['avg_Bps']:,.0f} B/s, max {r['max_Bps']:,.0f} B/s, "
                                           f"{r['bytes_per_changed_voxel']} B/changed voxel, x{r['compression_ratio']} compression, "
                                           f"{r['ratio_to_raw_sensor']} of raw sensor B/s"))
        if baseline is not None:
            compare(result, baseline, tolerance, LOG_COMPARED)
        emit(result, as_json, rows)
        return
    result = map_stats(map_file)
    if baseline is not None:
        compare(result, baseline, tolerance)
    emit(result, as_json, summary_rows(result))


@main.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="Output file; its suffix picks the format: .bt, .ply, .pcd or .png.")
@click.option("--free", "include_free", is_flag=True, help="Also write free voxels (.ply/.pcd, coloured).")
@click.option("--json", "as_json", is_flag=True, help="Print what was written as JSON.")
@handle_errors
def export(map_file, output, include_free, as_json):
    """Export a map snapshot: .bt (OctoMap binary), .ply/.pcd (voxel centres), .png (top view)."""
    from voxtool.api import export_map

    count = export_map(map_file, output, include_free)
    emit({"output": str(output), "items": count}, as_json, [("written", str(output)), ("items", f"{count:,}")])


def run() -> None:
    """The `voxtool` console command: main(), then an exit without the interpreter's teardown,
    which after a build spent 0.4-0.6 s releasing numba's compiled code. Every output is written,
    fsynced and renamed into place, and stdout/stderr are flushed, before this point."""
    try:
        main()
        code = 0
    except SystemExit as stop:
        code = stop.code
    if isinstance(code, str):
        print(code, file=sys.stderr)
        code = 1
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(code or 0)


if __name__ == "__main__":  # pragma: no cover
    run()
