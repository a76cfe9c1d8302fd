"""`voxtool merge`: fuse several robots' packet logs."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors, replay_for, view_options


@click.command()
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the fused state map (.vxm).")
@click.option("--extrinsic", multiple=True, help="ROBOT=tx,ty,tz,qw,qx,qy,qz: pose of that robot's map in the fused frame.")
@click.option("--simulate-loss", type=float, default=None, help="Run the request/response resend simulation with this loss rate.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Seed of the loss simulation.")
@click.option("--json", "as_json", is_flag=True, help="Print the fused map's figures, per robot, as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@view_options
@handle_errors
def merge(logs, output, extrinsic, simulate_loss, seed, as_json, progress, view, view_period, view_keyframe):
    """Fuse the packet logs of several robots: every voxel takes its latest-stamped state."""
    from voxtool.codec.fusion import Extrinsic, fuse, save_state_map

    ext = dict(Extrinsic.parse(e) for e in extrinsic)
    replay = replay_for(view, view_period, view_keyframe)
    result = fuse(list(logs), ext, progress=progress, on_packet=replay.packet if replay else None)
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
    if replay is not None:
        out.update(replay.write())
        rows.append(("view", f"{out['view']} ({out['view_messages']} SceneUpdates, {out['view_keyframes']} keyframes, colours {out['view_colours']})"))
    emit(out, as_json, rows, written=output)
