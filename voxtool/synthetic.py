"""Generated LiDAR scenes with moving objects and per-point ground truth (for `clean`'s tests
and benchmarks/bench_clean.py).

A street: a ground plane, buildings, poles and parked cars (static boxes), and movers (cars,
cyclists, pedestrians: boxes moving at constant velocity). A spinning multi-beam LiDAR on a
vehicle casts exact rays against them; the range gets Gaussian noise. Each point is labelled
dynamic when the surface it hit belongs to a mover.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Box:
    """An axis-aligned box at time 0 and its constant velocity (m/s)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def moving(self) -> bool:
        return any(v != 0.0 for v in self.velocity)


@dataclass(frozen=True)
class Lidar:
    """A spinning LiDAR: beams at evenly spread elevations, `columns` azimuth steps per turn."""

    beams: int = 32
    columns: int = 1024
    min_elevation_deg: float = -25.0
    max_elevation_deg: float = 15.0
    max_range: float = 60.0
    range_noise: float = 0.02  # metres, standard deviation

    def directions(self) -> np.ndarray:
        el = np.radians(np.linspace(self.min_elevation_deg, self.max_elevation_deg, self.beams))
        az = np.linspace(0.0, 2 * np.pi, self.columns, endpoint=False)
        e, a = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)


@dataclass
class Scene:
    """Boxes, the sensor's path and the scan rate; `scans()` renders it."""

    boxes: list[Box]
    lidar: Lidar = field(default_factory=Lidar)
    n_scans: int = 30
    rate_hz: float = 10.0
    sensor_start: tuple[float, float, float] = (-10.0, -1.5, 1.8)
    sensor_velocity: tuple[float, float, float] = (3.0, 0.0, 0.0)
    sensor_yaw_rate: float = 0.05  # rad/s: the sensor frame turns, so poses carry a rotation
    seed: int = 0

    def scans(self):
        """Yield (world points float32, sensor origin float64, yaw, dynamic labels bool) per scan."""
        rng = np.random.default_rng(self.seed)
        dirs_sensor = self.lidar.directions()
        for i in range(self.n_scans):
            t = i / self.rate_hz
            origin = np.asarray(self.sensor_start) + t * np.asarray(self.sensor_velocity)
            yaw = t * self.sensor_yaw_rate
            c, s = np.cos(yaw), np.sin(yaw)
            dirs = dirs_sensor @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # R(yaw) d
            dist, moving = first_hits(origin, dirs, self.boxes, t, self.lidar.max_range)
            hit = np.isfinite(dist)
            r = dist[hit] + rng.normal(0.0, self.lidar.range_noise, int(hit.sum()))
            points = (origin + dirs[hit] * r[:, None]).astype(np.float32)
            yield points, origin, yaw, moving[hit]


def first_hits(origin: np.ndarray, dirs: np.ndarray, boxes: list[Box], t: float,
               max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the first surface along each ray (inf: none within max_range; the ground is
    z = 0) and whether that surface is a moving box (slab test, all rays x all boxes at once)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ground = np.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], np.inf)
    best = np.where(ground <= max_range, ground, np.inf)
    moving = np.zeros(dirs.shape[0], dtype=bool)
    if boxes:
        first, which = box_entries(origin, dirs, boxes, t)
        closer = (first < best) & (first <= max_range)
        best = np.where(closer, first, best)
        moving = closer & np.array([b.moving for b in boxes])[which]
    return best, moving


def box_entries(origin: np.ndarray, dirs: np.ndarray, boxes: list[Box], t: float) -> tuple[np.ndarray, np.ndarray]:
    """(distance along each unit ray to where it first enters one of the boxes at time t, inf
    where none; which box), by the slab test, every ray against every box at once. A ray that
    starts inside a box does not enter it."""
    shift = np.array([b.velocity for b in boxes]) * t
    lo = np.array([b.lo for b in boxes]) + shift
    hi = np.array([b.hi for b in boxes]) + shift
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs  # (N, 3); inf along an axis the ray does not move in
        t1 = (lo[None, :, :] - origin) * inv[:, None, :]
        t2 = (hi[None, :, :] - origin) * inv[:, None, :]
        near = np.nanmax(np.minimum(t1, t2), axis=2)
        far = np.nanmin(np.maximum(t1, t2), axis=2)
    entry = np.where((near <= far) & (far > 0) & (near > 0), near, np.inf)
    which = np.argmin(entry, axis=1)
    return entry[np.arange(dirs.shape[0]), which], which


def insert_movers(points: np.ndarray, origin: np.ndarray, t: float, boxes: list[Box]) -> tuple[np.ndarray, np.ndarray]:
    """A real scan with moving boxes ray-traced into it: every ray (origin -> its real return)
    is kept, and where a box at time t lies in front of the return the ray stops at the box's
    surface. Returns (the points, float32; which of them lie on a box: the dynamic truth)."""
    if not boxes or points.shape[0] == 0:
        return np.asarray(points, dtype=np.float32), np.zeros(points.shape[0], dtype=bool)
    o = np.asarray(origin, dtype=np.float64)
    out = np.array(points, dtype=np.float64)  # a copy: the returns the boxes hide are moved
    v = out - o
    length = np.linalg.norm(v, axis=1)
    dirs = v / np.where(length > 0, length, 1.0)[:, None]
    entry, _ = box_entries(o, dirs, boxes, t)
    hit = entry < length
    out[hit] = o + dirs[hit] * entry[hit, None]
    return out.astype(np.float32), hit


def street(n_scans: int = 30, seed: int = 0, lidar: Lidar | None = None) -> Scene:
    """A street 60 m long: buildings on both sides, poles, parked cars; two cars at 8 and 12 m/s
    in the lanes, a cyclist at 4 m/s, three pedestrians at 1-1.5 m/s crossing or walking."""
    static = [
        Box((-30.0, 8.0, 0.0), (30.0, 14.0, 9.0)),  # buildings
        Box((-30.0, -14.0, 0.0), (-2.0, -8.0, 12.0)),
        Box((2.0, -14.0, 0.0), (30.0, -8.0, 7.0)),
        Box((-4.0, 5.5, 0.0), (0.5, 7.3, 1.5)),  # parked cars
        Box((6.0, 5.5, 0.0), (10.5, 7.3, 1.6)),
        *[Box((x, -7.0, 0.0), (x + 0.3, -6.7, 4.0)) for x in (-15.0, -5.0, 5.0, 15.0)],  # poles
    ]
    movers = [
        Box((-25.0, 1.0, 0.0), (-20.5, 2.8, 1.5), (8.0, 0.0, 0.0)),  # car, this lane, overtaking
        Box((20.0, -4.5, 0.0), (24.5, -2.7, 1.6), (-12.0, 0.0, 0.0)),  # car, oncoming lane
        Box((-12.0, 4.0, 0.0), (-10.2, 4.6, 1.7), (4.0, 0.0, 0.0)),  # cyclist
        Box((3.0, -7.5, 0.0), (3.5, -7.0, 1.8), (0.0, 1.2, 0.0)),  # pedestrians crossing
        Box((-6.0, 7.0, 0.0), (-5.5, 7.5, 1.7), (0.3, -1.0, 0.0)),
        Box((12.0, -7.8, 0.0), (12.5, -7.3, 1.75), (-1.5, 0.0, 0.0)),  # walking on the pavement
    ]
    return Scene(static + movers, lidar or Lidar(), n_scans=n_scans, seed=seed)


def write_pcd_scans(scene: Scene, directory: str | Path) -> np.ndarray:
    """Write the scene as a PCD directory voxtool reads (sensor-frame points, VIEWPOINT = pose)
    with poses.txt (TUM rows: the scan times, which voxtool reads from beside the scans) and return the ground-truth dynamic
    labels of every point, in read order."""
    from voxtool.io.export import pcd_header, pcd_rows

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    labels, poses = [], []
    for i, (points, origin, yaw, moving) in enumerate(scene.scans()):
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        local = ((points.astype(np.float64) - origin) @ rot).astype(np.float32)  # R^T (p - t)
        viewpoint = (*origin, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        (directory / f"{i:06d}.pcd").write_bytes(pcd_header(len(local), False, viewpoint=viewpoint) + pcd_rows(local, None))
        labels.append(moving)
        poses.append(f"{i / scene.rate_hz:.6f} {origin[0]:.9f} {origin[1]:.9f} {origin[2]:.9f} "
                     f"0 0 {np.sin(yaw / 2):.12f} {np.cos(yaw / 2):.12f}\n")
    (directory / "poses.txt").write_text("".join(poses))
    return np.concatenate(labels)


def ground_height(points: np.ndarray, origin: np.ndarray) -> float:
    """The ground's height under a real scan: the most common height (0.1 m bins) of the points
    3-25 m from the sensor horizontally and at least 0.3 m below it."""
    d = np.linalg.norm(points[:, :2] - origin[:2], axis=1)
    z = points[(d > 3.0) & (d < 25.0) & (points[:, 2] < origin[2] - 0.3), 2]
    if z.size < 50:
        return float(origin[2]) - 1.8
    counts, edges = np.histogram(z, bins=np.arange(z.min(), z.max() + 0.2, 0.1))
    return float(edges[int(np.argmax(counts))])


# (what, along, side, length, width, height, speed along the travel, speed across, the speed along
# is the sensor's plus this): where each is when the sensor is half way through the scans, in
# metres from it (along its travel, to its left), and how it moves (m/s)
TRAFFIC = [
    ("car, oncoming", 14.0, 3.0, 4.5, 1.8, 1.5, -10.0, 0.0, False),
    ("car, overtaking", -3.0, -3.2, 4.5, 1.8, 1.5, 6.0, 0.0, True),
    ("cyclist", 7.0, -5.0, 1.8, 0.6, 1.7, 4.0, 0.0, False),
    ("pedestrian, crossing", 10.0, -6.0, 0.5, 0.5, 1.75, 0.0, 1.3, False),
    ("pedestrian, crossing", 16.0, 6.5, 0.5, 0.5, 1.7, 0.0, -1.2, False),
    ("pedestrian, walking", 5.0, 5.5, 0.5, 0.5, 1.8, -1.2, 0.0, False),
]


def traffic(origins: np.ndarray, times: np.ndarray, ground_z: float) -> list[Box]:
    """Moving boxes for a real sequence (sensor origins and scan times in seconds): two cars (one
    oncoming at 10 m/s, one overtaking the sensor by 6 m/s), a cyclist and pedestrians at
    realistic sizes and speeds, standing on the ground, placed (TRAFFIC) around where the sensor
    is half way through, along its direction of travel (the x axis for a sensor that stays put).
    A box that would hold the sensor at some scan is left out."""
    origins = np.asarray(origins, dtype=np.float64)
    travel = origins[-1, :2] - origins[0, :2]
    span = float(times[-1] - times[0]) if len(times) > 1 else 0.0
    moved = float(np.linalg.norm(travel))
    heading = travel / moved if moved > 1.0 else np.array([1.0, 0.0])
    left = np.array([-heading[1], heading[0]])
    speed = moved / span if span > 0 and moved > 1.0 else 0.0
    mid = len(origins) // 2
    centre, t_mid = origins[mid, :2], float(times[mid] - times[0])
    boxes = []
    for _, along, side, length, width, height, v_along, v_side, relative in TRAFFIC:
        position = centre + along * heading + side * left
        velocity = (v_along + (speed if relative else 0.0)) * heading + v_side * left
        extent = np.array([length, width]) if abs(heading[0]) >= abs(heading[1]) else np.array([width, length])
        if v_side and not v_along:  # crossing: its length lies across the travel
            extent = extent[::-1]
        lo = np.array([*(position - extent / 2 - velocity * t_mid), ground_z])
        hi = np.array([*(position + extent / 2 - velocity * t_mid), ground_z + height])
        box = Box(tuple(lo), tuple(hi), (float(velocity[0]), float(velocity[1]), 0.0))
        shifts = np.outer(np.asarray(times, dtype=np.float64) - times[0], box.velocity)
        if not np.any(np.all((origins >= lo + shifts) & (origins <= hi + shifts), axis=1)):
            boxes.append(box)
    return boxes


@dataclass(frozen=True)
class PoseError:
    """Error of a survey-grade GNSS/INS pose (standard deviations, independent per scan: the worst
    case for scans a tenth of a second apart; an RTK-corrected INS specifies 2 cm horizontal and
    0.03 degrees of roll and pitch, 0.1 degrees of heading, and twice as much vertical error is
    usual)."""

    horizontal_m: float = 0.03
    vertical_m: float = 0.05
    roll_pitch_deg: float = 0.05
    heading_deg: float = 0.1
    # a real INS also drifts, the same way for seconds: against LiDAR odometry over 6 s of KITTI raw
    # frames, z moved 35 cm and pitch 0.4 degrees. The drift's rates (0: none), applied at scan time t
    drift_z_m_s: float = 0.0
    drift_pitch_deg_s: float = 0.0

    @classmethod
    def drifting(cls) -> PoseError:
        """Survey-grade error plus the drift measured on KITTI raw (35 cm and 0.4 degrees in 6 s)."""
        return cls(drift_z_m_s=0.35 / 6.0, drift_pitch_deg_s=0.4 / 6.0)

    def apply(self, points: np.ndarray, origin: np.ndarray, rng: np.random.Generator,
              t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """A scan (world points, sensor origin) taken at time t (seconds from the first) as a pose
        with this error places it: turned about the sensor by a random small rotation (and the
        drift's pitch by then) and shifted (and the drift's rise); returns (points float32, origin)."""
        rx, ry, rz = np.radians(rng.normal(0.0, [self.roll_pitch_deg, self.roll_pitch_deg, self.heading_deg]))
        ry += np.radians(self.drift_pitch_deg_s * t)
        cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
        turn = (np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
                @ np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
                @ np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]]))
        o = np.asarray(origin, dtype=np.float64)
        shifted = o + rng.normal(0.0, [self.horizontal_m, self.horizontal_m, self.vertical_m]) + [0.0, 0.0,
                                                                                                   self.drift_z_m_s * t]
        return ((np.asarray(points, dtype=np.float64) - o) @ turn.T + shifted).astype(np.float32), shifted
