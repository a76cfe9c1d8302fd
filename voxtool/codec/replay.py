"""How a map was shared and fused, for a viewer (`decode --view` / `merge --view OUT.mcap`).

An MCAP of foxglove.SceneUpdate messages (Foxglove's protobuf schema package) on `/voxtool/fusion`,
one message per `period` of packet time (and one after the last packet), in fusion order. Each
robot's occupied voxels are drawn as cubes in that robot's colour: a voxel belongs to the robot
whose packet set it last (the fusion rule). Re-sending a robot's whole map at every step would
cost its full size each time, so the voxels are grouped in blocks of 16^3 and a message carries
only the blocks that packets touched since the one before: entity `<robot>/<block>` is replaced
(Foxglove's rule for an entity id), or deleted when the robot holds nothing in it any more.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.codec.packet import OCCUPIED
from voxtool.keys import TREE_MAX_VAL, morton_decode
from voxtool.plots import series_colour

TOPIC = "/voxtool/fusion"
BLOCK_BITS = 12  # 16^3 voxels: a block is the unit a message re-sends


class Replay:
    """Collects the fused state packet by packet and writes SceneUpdates of what changed."""

    def __init__(self, path: Path, period_s: float = 1.0) -> None:
        self.path, self.period_ns = Path(path), int(period_s * 1e9)
        self.codes = np.zeros(0, np.int64)  # sorted Morton codes of voxels a packet set
        self.states = np.zeros(0, np.uint8)
        self.owners = np.zeros(0, np.int16)  # index into self.robots
        self.robots: list[str] = []
        self.dirty: set[int] = set()
        self.drawn: set[str] = set()  # entity ids on screen
        self.messages: list[tuple[int, bytes]] = []
        self.resolution = None
        self.last_emit = None
        self.stamp = 0

    def packet(self, packet, codes: np.ndarray) -> None:
        """Record one fused packet (fuse's on_packet)."""
        if self.last_emit is not None and packet.stamp_ns - self.last_emit >= self.period_ns:
            self._emit()
        if self.last_emit is None:
            self.last_emit = packet.stamp_ns
        self.resolution = packet.resolution
        self.stamp = packet.stamp_ns
        if packet.robot not in self.robots:
            self.robots.append(packet.robot)
        owner = self.robots.index(packet.robot)
        # the packet's voxels replace earlier states of the same voxels (latest wins)
        codes_all = np.concatenate([self.codes, codes])
        states_all = np.concatenate([self.states, packet.states])
        owners_all = np.concatenate([self.owners, np.full(len(codes), owner, np.int16)])
        order = np.argsort(codes_all, kind="stable")
        codes_all = codes_all[order]
        last = np.ones(len(codes_all), bool)
        last[:-1] = codes_all[1:] != codes_all[:-1]
        self.codes, self.states, self.owners = codes_all[last], states_all[order][last], owners_all[order][last]
        self.dirty.update(np.unique(codes >> BLOCK_BITS).tolist())

    def _emit(self) -> None:
        from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

        from voxtool.io.viewer_mcap import scene_entity

        update = SceneUpdate()
        blocks = np.array(sorted(self.dirty), np.int64)
        inside = np.isin(self.codes >> BLOCK_BITS, blocks) & (self.states == OCCUPIED)
        codes, owners = self.codes[inside], self.owners[inside]
        keys = morton_decode(codes).astype(np.float64)
        centres = (keys - TREE_MAX_VAL + 0.5) * self.resolution
        block_of = codes >> BLOCK_BITS
        shown = set()
        for owner, robot in enumerate(self.robots):
            mine = owners == owner
            rgba = (*series_colour(owner), 1.0)
            for block in np.unique(block_of[mine]):
                sel = mine & (block_of == block)
                entity_id = f"{robot}/{int(block):x}"
                update.entities.append(scene_entity(entity_id, centres[sel], np.full(int(sel.sum()), self.resolution),
                                                    np.tile(rgba, (int(sel.sum()), 1)), self.stamp))
                shown.add(entity_id)
        dirty_ids = {f"{robot}/{int(b):x}" for robot in self.robots for b in blocks}
        for entity_id in sorted((self.drawn & dirty_ids) - shown):
            deletion = SceneEntityDeletion(id=entity_id, type=SceneEntityDeletion.MATCHING_ID)
            deletion.timestamp.FromNanoseconds(self.stamp)
            update.deletions.append(deletion)
        self.drawn = (self.drawn - dirty_ids) | shown
        self.dirty.clear()
        self.last_emit = self.stamp
        self.messages.append((self.stamp, update.SerializeToString()))

    def write(self) -> dict:
        """Emit what is pending and write the MCAP (atomically)."""
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
        from matplotlib.colors import to_hex
        from mcap.writer import Writer
        from mcap_protobuf.schema import register_schema

        from voxtool.atomic import atomic_writer

        if self.dirty or not self.messages:
            self._emit()
        with atomic_writer(self.path) as handle:
            writer = Writer(handle)
            writer.start(profile="", library="voxtool")
            schema = register_schema(writer, SceneUpdate)
            channel = writer.register_channel(TOPIC, "protobuf", schema)
            for seq, (stamp, data) in enumerate(self.messages):
                writer.add_message(channel, stamp, data, stamp, sequence=seq)
            writer.finish()
        return {"view": str(self.path), "view_messages": len(self.messages),
                "view_colours": {robot: to_hex(series_colour(i)) for i, robot in enumerate(self.robots)}}

