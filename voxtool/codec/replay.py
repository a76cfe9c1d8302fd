"""How a map was shared and fused, for a viewer (`decode --view` / `merge --view OUT.mcap`).

An MCAP of ROS 2 foxglove_msgs/msg/SceneUpdate messages (voxtool.io.ros2) on `/voxtool/fusion`,
in fusion order; Foxglove, rosbags and ROS 2 tools open it. A message holds every packet up to
its time and is stamped with the last one's: the first at the first packet time, each next one
at the first packet time at least `period` after it (0: every distinct packet time), and one at
the last packet. Each robot's occupied voxels are drawn as cubes in that robot's colour: a voxel
belongs to the robot whose packet set it last (the fusion rule). Re-sending a robot's whole map
at every step would cost its full size each time, so the voxels are grouped in blocks of 16^3
and a message carries only the blocks that packets touched since the one before: entity
`<robot>/<block>` is replaced (Foxglove's rule for an entity id), or deleted when the robot
holds nothing in it any more. So that a viewer that seeks, or starts reading mid-file, can show
the whole map, a message at least `keyframe` seconds of packet time after the last keyframe
(and the first message) is a keyframe: a deletion of every entity, then every block of every
robot, the whole fused map at that time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.codec.packet import OCCUPIED
from voxtool.keys import keys_to_coords, morton_decode
from voxtool.plots import series_colour

TOPIC = "/voxtool/fusion"
SCENE = "foxglove_msgs/msg/SceneUpdate"
BLOCK_BITS = 12  # 16^3 voxels: a block is the unit a message re-sends


class Replay:
    """Collects the fused state packet by packet and writes SceneUpdates of what changed."""

    def __init__(self, path: Path, period_s: float = 1.0, keyframe_s: float = 10.0) -> None:
        self.path, self.period_ns, self.keyframe_ns = Path(path), int(period_s * 1e9), int(keyframe_s * 1e9)
        # only the occupied voxels are drawn, so only they are kept: a later free or unknown
        # state of a voxel removes it (millions of free voxels would make every merge slow)
        self.codes = np.zeros(0, np.int64)  # sorted Morton codes of the voxels occupied now
        self.owners = np.zeros(0, np.int16)  # the robot (index into self.robots) that set each
        self.robots: list[str] = []
        self.dirty: set[int] = set()
        self.drawn: set[str] = set()  # entity ids on screen
        self.messages: list[tuple[int, bytes]] = []
        self.resolution = None
        self.last_emit = None
        self.last_keyframe = None
        self.keyframes = 0
        self.stamp = 0

    def packet(self, packet, codes: np.ndarray) -> None:
        """Record one fused packet (fuse's on_packet)."""
        # what is pending goes out once a later packet shows that its time is complete
        if self.dirty and packet.stamp_ns != self.stamp and (
                self.last_emit is None or self.stamp - self.last_emit >= self.period_ns):
            self._emit()
        self.resolution = packet.resolution
        self.stamp = packet.stamp_ns
        if packet.robot not in self.robots:
            self.robots.append(packet.robot)
        owner = self.robots.index(packet.robot)
        # the packet's voxels replace earlier states of the same voxels (latest wins)
        order = np.argsort(codes, kind="stable")
        new_codes, new_states = codes[order], packet.states[order]
        last = np.ones(len(new_codes), bool)
        last[:-1] = new_codes[1:] != new_codes[:-1]  # a voxel twice in one packet: its last state
        new_codes, occupied = new_codes[last], new_states[last] == OCCUPIED
        at = np.searchsorted(self.codes, new_codes)
        known = at < len(self.codes)
        known[known] = self.codes[at[known]] == new_codes[known]
        self.owners[at[known & occupied]] = owner
        gone = at[known & ~occupied]
        if gone.size:
            self.codes, self.owners = np.delete(self.codes, gone), np.delete(self.owners, gone)
        fresh = new_codes[~known & occupied]
        if fresh.size:
            where = np.searchsorted(self.codes, fresh)
            self.codes = np.insert(self.codes, where, fresh)
            self.owners = np.insert(self.owners, where, np.int16(owner))
        self.dirty.update(np.unique(new_codes >> BLOCK_BITS).tolist())

    def _emit(self) -> None:
        from voxtool.io.ros2 import msg, serialize, stamp
        from voxtool.io.viewer_mcap import scene_entity, scene_message

        entities, deletions = [], []
        deletion = msg("foxglove_msgs/msg/SceneEntityDeletion")
        keyframe = self.last_keyframe is None or self.stamp - self.last_keyframe >= self.keyframe_ns
        if keyframe:  # every entity goes, every block of every robot comes
            deletions.append(deletion(timestamp=stamp(self.stamp), type=deletion.ALL, id=""))
            self.dirty.update(np.unique(self.codes >> BLOCK_BITS).tolist())
            self.drawn = set()
            self.last_keyframe = self.stamp
            self.keyframes += 1
        blocks = np.array(sorted(self.dirty), np.int64)
        # a block's voxels are one run of the sorted codes (a block is a Morton prefix)
        lo = np.searchsorted(self.codes, blocks << BLOCK_BITS)
        hi = np.searchsorted(self.codes, (blocks + 1) << BLOCK_BITS)
        inside = np.concatenate([np.arange(a, b) for a, b in zip(lo.tolist(), hi.tolist())] or [np.zeros(0, np.int64)])
        codes, owners = self.codes[inside], self.owners[inside]
        centres = keys_to_coords(morton_decode(codes), self.resolution)
        block_of = codes >> BLOCK_BITS
        shown = set()
        # one entity per (robot, block): runs of the voxels sorted by owner, then block
        order = np.lexsort((block_of, owners))
        pairs = np.column_stack([owners[order], block_of[order]])
        starts = np.flatnonzero(np.r_[True, (pairs[1:] != pairs[:-1]).any(axis=1)]) if len(order) else np.zeros(0, int)
        for a, b in zip(starts.tolist(), np.append(starts[1:], len(order)).tolist()):
            owner, block = int(pairs[a, 0]), int(pairs[a, 1])
            sel = order[a:b]
            entity_id = f"{self.robots[owner]}/{block:x}"
            rgba = (*series_colour(owner), 1.0)
            entities.append(scene_entity(entity_id, centres[sel], np.full(b - a, self.resolution),
                                         np.tile(rgba, (b - a, 1)), self.stamp))
            shown.add(entity_id)
        dirty_ids = {f"{robot}/{int(b):x}" for robot in self.robots for b in blocks}
        for entity_id in sorted((self.drawn & dirty_ids) - shown):
            deletions.append(deletion(timestamp=stamp(self.stamp), type=deletion.MATCHING_ID, id=entity_id))
        self.drawn = (self.drawn - dirty_ids) | shown
        self.dirty.clear()
        self.last_emit = self.stamp
        self.messages.append((self.stamp, serialize(scene_message(entities, deletions), SCENE)))

    def write(self) -> dict:
        """Emit what is pending and write the MCAP (atomically)."""
        from matplotlib.colors import to_hex

        from voxtool.atomic import atomic_writer
        from voxtool.io.ros2 import Ros2McapWriter

        if self.dirty or not self.messages:
            self._emit()
        with atomic_writer(self.path) as handle:
            writer = Ros2McapWriter(handle)
            channel = writer.channel(TOPIC, SCENE)
            for stamp_ns, data in self.messages:
                writer.write_serialized(channel, data, stamp_ns)
            writer.finish()
        return {"view": str(self.path), "view_messages": len(self.messages), "view_keyframes": self.keyframes,
                "view_colours": {robot: to_hex(series_colour(i)) for i, robot in enumerate(self.robots)}}

