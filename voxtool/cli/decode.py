"""`voxtool decode`: replay a packet log into a state map."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors, replay_for, summary_rows, view_options


@click.command()
@click.argument("log", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the replayed state map as a snapshot (.vxm).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON (with every packet's header).")
@click.option("--voxels", is_flag=True, help="--json: also list every packet's voxels as [x, y, z key, state].")
@click.option("--relay", is_flag=True, help="Integrate 'occupied' frames into a hash map like sensor hits (receiver side).")
@click.option("--d-inf", default=0.2, show_default=True, type=float, help="--relay: inflation radius of the receiving hash map.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@view_options
@handle_errors
def decode(log, output, as_json, voxels, relay, d_inf, progress, view, view_period, view_keyframe):
    """Replay a packet log into a state map (free / occupied / unknown)."""
    from voxtool.codec.fusion import fuse, packets_of, save_state_map

    if relay and view is not None:
        from voxtool.errors import ParameterError

        raise ParameterError("--view replays the packets' voxel states; --relay integrates frames into a hash map instead")
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
        emit(result, as_json, summary_rows(result), written=output)
        return

    replay = replay_for(view, view_period, view_keyframe)
    result = fuse([log], progress=progress, on_packet=replay.packet if replay else None)
    occ = int((result.states == 1).sum())
    data = {"log": str(log), "packets": result.packets, "occupied_voxels": occ,
            "free_voxels": int(result.states.shape[0] - occ), "resolution": result.resolution, "robots": result.robots}
    if output is not None:
        save_state_map(output, result, {"source": str(log), "packets": result.packets})  # consumes the voxels
    if as_json:
        data["packet_headers"] = []
        for p in packets_of(log):
            head = {k: v for k, v in p.__dict__.items() if k not in ("keys", "states")}
            if voxels:
                head["voxels"] = [[int(a), int(b), int(c), int(s)] for (a, b, c), s in zip(p.keys, p.states)]
            data["packet_headers"].append(head)
    rows = [("packets", f"{result.packets:,}"), ("occupied voxels", f"{occ:,}"), ("free voxels", f"{data['free_voxels']:,}")]
    if replay is not None:
        data.update(replay.write())
        rows.append(("view", f"{data['view']} ({data['view_messages']} SceneUpdates, {data['view_keyframes']} keyframes)"))
    emit(data, as_json, rows, written=output)
