"""Procedural street scenes: layout, static clutter, agents and their motion.

World frame: x along the main street, y to its left, z up (metres); the ground is a slightly
sloped plane ``z = a x + b y`` plus a few centimetres of smooth roughness. Right-hand traffic:
lanes with ``y < 0`` drive towards +x, lanes with ``y > 0`` towards -x. Each side of the road,
from the centre line out: driving lanes, a bike lane, an optional parking lane, a raised sidewalk
(kerb zone with trees, poles, signs and bike racks; then a walking zone), then buildings, walls
and hedges. An optional cross street cuts the blocks; some vehicles turn right into it.

Everything random is drawn from ``numpy.random.default_rng([seed, scene_id])`` in a fixed order,
so a scene is a pure function of ``(seed, scene_id, config)``.
"""

from __future__ import annotations

import math

import numpy as np

from envs.synthetic.kitti_motion import KittiMotion, scene_plan
from envs.synthetic.motion import cumdist, drift, lane_path, polyline_walk, speed_profile, walk
from envs.synthetic.objects import make_object, sample_size
from envs.synthetic.raycast import BOX, CYLINDER, ELLIPSOID, Parts
from envs.synthetic.scene_types import FOV_HALF_ANGLE, Agent, Ground, Scene, SceneConfig

__all__ = ["StaticObject", "build_scene", "make_pole", "make_tree"]

_RACK_CLEAR_M = 1.5  # metres of parking lane kept free on either side of a bike rack
_RACK_VIEW_M = 15.0  # and before the guaranteed rack / pedestrian (line of sight from the road)
_F = np.float32


class StaticObject:
    """Accumulates static objects (world frame)."""

    def __init__(self) -> None:
        self.bounds: list[np.ndarray] = []
        self.solid: list[bool] = []
        self.refl: list[float] = []
        self.parts: list[Parts] = []

    def solid_box(self, x, y, z0, l, w, h, yaw, refl) -> None:
        self.bounds.append(np.array([x, y, z0 + h / 2, l, w, h, yaw], dtype=np.float64))
        self.solid.append(True)
        self.refl.append(refl)

    def composite(self, parts: Parts, bounds: np.ndarray) -> None:
        idx = len(self.bounds)
        self.bounds.append(np.asarray(bounds, dtype=np.float64))
        self.solid.append(False)
        self.refl.append(0.0)
        parts.owner = np.full(len(parts), idx, dtype=np.int64)
        self.parts.append(parts)


def _single(kind: int, center, half, refl: float, rot=None) -> Parts:
    return Parts(
        np.array([kind], np.int8),
        np.asarray(center, float).reshape(1, 3),
        (np.eye(3) if rot is None else np.asarray(rot, float)).reshape(1, 3, 3),
        np.asarray(half, float).reshape(1, 3),
        np.array([refl], _F),
        np.zeros(1, np.int64),
    )


def make_tree(st: StaticObject, g: Ground, x: float, y: float, rng: np.random.Generator) -> None:
    z = float(g.height(x, y))
    r_t = rng.uniform(0.1, 0.25)
    crown_r = rng.uniform(1.2, 2.6)
    crown_h = rng.uniform(1.4, 3.0)
    trunk_top = rng.uniform(2.0, 3.5)
    top = trunk_top + 2 * crown_h * 0.85
    parts = Parts.concat(
        [
            _single(
                CYLINDER, (x, y, z + trunk_top / 2 + 0.3), (r_t, r_t, trunk_top / 2 + 0.3), 0.3
            ),
            _single(
                ELLIPSOID,
                (x, y, z + trunk_top + crown_h * 0.85),
                (crown_r, crown_r * 0.9, crown_h),
                0.2,
            ),
        ]
    )
    st.composite(parts, [x, y, z + top / 2, 2 * crown_r, 2 * crown_r, top + 0.2, 0.0])


def make_pole(
    st: StaticObject, g: Ground, x: float, y: float, rng: np.random.Generator, side: float
):
    z = float(g.height(x, y))
    if rng.random() < 0.5:  # street lamp with an arm over the road
        hgt = rng.uniform(6.0, 8.5)
        arm = rng.uniform(1.0, 2.0)
        parts = Parts.concat(
            [
                _single(CYLINDER, (x, y, z + hgt / 2), (0.09, 0.09, hgt / 2), 0.5),
                _single(BOX, (x, y - side * arm / 2, z + hgt - 0.1), (0.15, arm / 2, 0.08), 0.5),
            ]
        )
        st.composite(
            parts, [x, y - side * arm / 2, z + hgt / 2 + 0.1, 0.4, arm + 0.2, hgt + 0.2, 0.0]
        )
    else:  # traffic sign: thin pole and a retro-reflective plate (bright in intensity)
        hgt = rng.uniform(2.2, 3.0)
        parts = Parts.concat(
            [
                _single(CYLINDER, (x, y, z + hgt / 2), (0.04, 0.04, hgt / 2), 0.5),
                _single(BOX, (x, y, z + hgt + 0.3), (0.03, 0.35, 0.3), 0.95),
            ]
        )
        st.composite(parts, [x, y, z + (hgt + 0.6) / 2, 0.2, 0.8, hgt + 0.7, 0.0])


def build_scene(
    scene_id: int, seed: int, config: SceneConfig, motion_params: KittiMotion | None = None
) -> Scene:
    """Generate scene ``scene_id`` of the world with ``seed`` (``motion_params``: constants of
    the ``"kitti"`` motion other than the fitted ones, for ``experiments/fit_motion.py``)."""
    rng = np.random.default_rng([int(seed), int(scene_id), 7])
    n = config.n_frames
    dens, sdens = config.density, config.static_density
    plan = scene_plan(config.motion, seed, scene_id, motion_params)  # None: v1, written here

    # ---- road layout
    lane_w = rng.uniform(3.2, 3.7)
    n_lanes = 1 if rng.random() < 0.6 else 2
    bike_w = 1.5
    park_r = True
    park_l = bool(rng.random() < 0.6)
    park_w = 2.3
    drive = n_lanes * lane_w
    edge_r = -(drive + bike_w + (park_w if park_r else 0.0))
    edge_l = drive + bike_w + (park_w if park_l else 0.0)
    sidewalk = rng.uniform(2.5, 4.5)
    curb_h = rng.uniform(0.1, 0.16)

    # ---- ego motion
    standing = rng.random() < 0.15
    v_ego = speed_profile(rng, n, 0.0 if standing else rng.uniform(3.0, 11.0), 0.1)
    if plan is not None:
        standing, v_ego = plan.ego_speed(n)
    ego_lane = -(int(rng.integers(0, n_lanes)) + 0.5) * lane_w
    s_ego = cumdist(v_ego)
    wiggle = 0.15 * np.sin(s_ego / rng.uniform(20.0, 60.0) + rng.uniform(0, 2 * np.pi))
    ego = np.stack([s_ego, ego_lane + wiggle, np.zeros(n)], 1)
    ego[1:, 2] = np.arctan2(np.diff(ego[:, 1]), np.maximum(np.diff(ego[:, 0]), 1e-3))
    ego[0, 2] = ego[1, 2] if n > 1 else 0.0
    if plan is not None:
        offset, heading = plan.ego_lateral(s_ego)
        ego[:, 1], ego[:, 2] = ego_lane + offset, heading
    x_min, x_max = -40.0, float(s_ego[-1]) + 90.0

    has_cross = rng.random() < 0.5
    cross_x = float(s_ego[n // 2] + rng.uniform(15.0, 45.0)) if has_cross else math.nan
    cross_half = drive + 1.0

    markings = (
        [0.0] + [k * lane_w for k in range(1, n_lanes)] + [-k * lane_w for k in range(1, n_lanes)]
    )
    k_mag = 2 * np.pi / rng.uniform(2.0, 15.0, 3)
    k_dir = rng.uniform(0, 2 * np.pi, 3)
    ground = Ground(
        slope_x=float(rng.normal(0.0, 0.01)),
        slope_y=float(rng.normal(0.0, 0.005)),
        rough_amp=rng.uniform(0.005, 0.02, 3),
        rough_k=np.stack([k_mag * np.cos(k_dir), k_mag * np.sin(k_dir)], 1),
        rough_phase=rng.uniform(0, 2 * np.pi, 3),
        road_y=(edge_r, edge_l),
        markings_y=np.array(markings),
        cross_x=cross_x,
        cross_half=cross_half,
        asphalt=float(rng.uniform(0.1, 0.2)),
        curb_h=curb_h,
        sidewalk_w=sidewalk,
    )

    def in_cross(x0: float, x1: float, margin: float = 0.0) -> bool:
        return (
            has_cross and x1 > cross_x - cross_half - margin and x0 < cross_x + cross_half + margin
        )

    # ---- static world
    st = StaticObject()
    kerb_x: dict[float, list[float]] = {}  # x of trees and poles in each kerb zone
    for side, edge in ((-1.0, edge_r), (1.0, edge_l)):
        # Sidewalk slabs in segments (tighter culling windows), cut at the cross street.
        x = x_min
        while x < x_max:
            # 10 m slabs: short enough that the level slab follows the sloped ground (and the
            # culling windows stay tight).
            seg = min(10.0, x_max - x)
            if not in_cross(x, x + seg):
                yc = edge + side * sidewalk / 2
                zc = float(ground.height(x + seg / 2, yc))
                st.solid_box(x + seg / 2, yc, zc - 0.3, seg, sidewalk, 0.3 + curb_h, 0.0, 0.3)
            x += seg
        # Buildings, walls and hedges behind the sidewalk.
        x = x_min + rng.uniform(-5, 5)
        while x < x_max:
            length = rng.uniform(6.0, 30.0)
            setback = rng.uniform(0.0, 3.0) if rng.random() < 0.5 else 0.0
            if not in_cross(x, x + length, 2.0):
                y_front = edge + side * (sidewalk + setback)
                kind = rng.random()
                if kind < 0.75:
                    depth = rng.uniform(8.0, 15.0)
                    hgt = rng.uniform(4.0, 18.0)
                    yc = y_front + side * depth / 2
                    st.solid_box(
                        x + length / 2,
                        yc,
                        float(ground.height(x, yc)) - 0.5,
                        length,
                        depth,
                        hgt + 0.5,
                        0.0,
                        float(rng.uniform(0.2, 0.6)),
                    )
                elif kind < 0.9:
                    hgt = rng.uniform(1.0, 2.2)
                    yc = y_front + side * 0.15
                    st.solid_box(
                        x + length / 2,
                        yc,
                        float(ground.height(x, yc)) - 0.2,
                        length,
                        0.3,
                        hgt + 0.2,
                        0.0,
                        float(rng.uniform(0.2, 0.6)),
                    )
                else:
                    hgt = rng.uniform(0.8, 1.6)
                    yc = y_front + side * 0.6
                    st.solid_box(
                        x + length / 2,
                        yc,
                        float(ground.height(x, yc)) - 0.2,
                        length,
                        1.2,
                        hgt + 0.2,
                        0.0,
                        0.18,
                    )
            x += length + (rng.uniform(0.0, 8.0) if rng.random() < 0.5 else 0.0)
        # Kerb-zone clutter: trees, poles, signs (kept apart from bike racks, see below).
        x = x_min + rng.uniform(0, 8)
        kerb_x[side] = []
        tree_gap = rng.uniform(7.0, 15.0)
        has_trees = rng.random() < 0.7
        while x < x_max:
            if not in_cross(x - 3, x + 3):
                y = edge + side * 0.6
                r = rng.random()
                if has_trees and r < 0.6 * min(sdens, 1.5):
                    make_tree(st, ground, x, y, rng)
                    kerb_x[side].append(x)
                elif r < 0.6 * min(sdens, 1.5) + 0.25 * sdens:
                    make_pole(st, ground, x, y + side * 0.1, rng, side)
                    kerb_x[side].append(x)
            x += tree_gap * rng.uniform(0.8, 1.2)

    agents: list[Agent] = []
    next_id = [0]

    def add_agent(category, model, pose, phase=None, amplitude=None) -> Agent:
        a = Agent(
            track_id=next_id[0],
            category=category,
            model=model,
            pose=np.asarray(pose, dtype=np.float64),
            phase=np.zeros(n) if phase is None else phase,
            amplitude=np.zeros(n) if amplitude is None else amplitude,
        )
        next_id[0] += 1
        agents.append(a)
        return a

    def static_pose(x, y, yaw) -> np.ndarray:
        return np.tile(np.array([x, y, yaw], dtype=np.float64), (n, 1))

    # Parking slots: list of occupied [x0, x1] per parking lane (collision-free by construction).
    park_slots: dict[float, list[tuple[float, float]]] = {-1.0: [], 1.0: []}

    def park(
        category: str, side: float, x_center: float, ridden: bool = False, clear_before: float = 0.0
    ) -> bool:
        if side > 0 and not park_l:
            return False
        size = sample_size(category, rng, ridden=ridden)
        yc = side * (drive + bike_w + park_w / 2)
        if category == "Motorcycle":  # parked across the lane
            half_x = size[1] / 2 + 0.2
            yaw = side * 0.5 * math.pi + rng.normal(0, 0.1)
            yc = side * (drive + bike_w + park_w - size[0] / 2 - 0.2)
        else:
            half_x = size[0] / 2
            yaw = (0.0 if side < 0 else math.pi) + rng.normal(0, 0.02)
            if rng.random() < 0.15:
                yaw += math.pi
            yc += side * rng.uniform(-0.15, 0.15)
        x0, x1 = x_center - half_x - 0.4 - clear_before, x_center + half_x + 0.4
        if in_cross(x0, x1, 3.0):
            return False
        if any(x0 < b and a < x1 for a, b in park_slots[side]):
            return False
        park_slots[side].append((x0, x1))
        model = make_object(category, size, rng, ridden=ridden)
        add_agent(category, model, static_pose(x_center, yc, yaw))
        return True

    def cyclist(
        category: str, side: float, x_mid: float, v_mean: float, alongside: bool = False
    ) -> None:
        size = sample_size(category, rng, ridden=True)
        model = make_object(category, size, rng, ridden=True)
        y = side * (drive + bike_w / 2)
        direction = -side
        if alongside:  # riding beside a slow ego, in and out of the field of view
            v = np.maximum(v_ego + drift(rng, n), 0.0)
            s = cumdist(v)
            x0 = float(ego[0, 0]) + abs(y - ego_lane) / math.tan(FOV_HALF_ANGLE)
            x0 += rng.uniform(1.0, 4.0)
        else:
            v = speed_profile(rng, n, v_mean, 0.05, accel=1.0)
            s = cumdist(v)
            # Position so that at mid-scene it is at x_mid.
            x0 = x_mid - direction * s[n // 2]
        pose = lane_path(s, x0, y, direction, None)
        phase = s / (2.1 * 2.5) * 2 * np.pi + rng.uniform(0, 2 * np.pi)
        add_agent(category, model, pose, phase, (v > 0.2).astype(float))

    def pedestrian(side: float, x0: float, standing: bool) -> None:
        size = sample_size("Pedestrian", rng)
        model = make_object("Pedestrian", size, rng)
        edge = edge_r if side < 0 else edge_l
        # Walking zone: behind the kerb zone (trees, poles, parked bicycles up to ~2 m).
        y_lo, y_hi = sorted(
            (edge + side * min(2.1, sidewalk - 0.5), edge + side * (sidewalk - 0.4))
        )
        y0 = rng.uniform(y_lo, max(y_hi, y_lo + 0.01))
        if standing:
            pose = static_pose(x0, y0, rng.uniform(-np.pi, np.pi))
            add_agent("Pedestrian", model, pose)
            return
        heading = 0.0 if rng.random() < 0.5 else math.pi
        speed = rng.uniform(0.9, 1.6)
        if rng.random() < 0.2:
            # Crossing the street: along the sidewalk, wait at the kerb, across, then on along
            # the far sidewalk. Crossings that would meet a vehicle are dropped later by the
            # overlap pass, so the survivors cross in gaps of the traffic.
            other = edge_l if side < 0 else edge_r
            y1 = other - side * rng.uniform(min(2.1, sidewalk - 0.5), sidewalk - 0.4)
            along = math.cos(heading)
            xk = x0 + along * rng.uniform(2.0, 12.0)
            pts = np.array(
                [
                    [x0, y0],
                    [xk, edge + side * 0.3],
                    [xk + along * 1.0, y1],
                    [xk + along * 40.0, y1],
                ]
            )
            pose, v = polyline_walk(rng, n, pts, speed, pause_at=1)
        else:
            noise = 0.02 if plan is None else plan.heading_noise
            pose, v = walk(rng, n, x0, y0, heading, y_lo, y_hi, speed, noise)
        stride = 1.45 * size[2] / 1.75
        phase = cumdist(v) / stride * 2 * np.pi + rng.uniform(0, 2 * np.pi)
        add_agent("Pedestrian", model, pose, phase, np.clip(v / 1.1, 0.0, 1.0))

    def bike_rack(side: float, x_center: float, count: int, clear_before: float = 0.0) -> None:
        """``count`` parked bicycles across the kerb. ``clear_before``: metres of parking lane
        kept free before the rack (towards -x, where the ego comes from), so that the rack is
        seen from afar over the empty lane instead of hidden behind parked cars."""
        edge = edge_r if side < 0 else edge_l
        # Slide along the kerb until clear of trees, poles and the cross street.
        # Racks stand where no vehicle parks in front of them (at a gap in the parking lane,
        # as real racks do at corners / no-parking stretches): a parked van or truck in front
        # would hide the ~1.1 m bicycles from the road for the whole scene.
        for _ in range(40):
            x0, x1 = x_center - 0.6, x_center + 0.75 * (count - 1) + 0.6
            clutter = np.asarray(kerb_x.get(side, []))
            free_x0, free_x1 = x0 - _RACK_CLEAR_M - clear_before, x1 + _RACK_CLEAR_M
            if (
                not in_cross(x0, x1, 1.0)
                and not ((clutter > x0 - 0.4) & (clutter < x1 + 0.4)).any()
                and not any(free_x0 < b and a < free_x1 for a, b in park_slots[side])
            ):
                break
            x_center += 2.0
        park_slots[side].append((free_x0, free_x1))
        for i in range(count):
            size = sample_size("Bicycle", rng, ridden=False)
            model = make_object("Bicycle", size, rng, ridden=False)
            y = edge + side * (0.3 + size[0] / 2)
            add_agent("Bicycle", model, static_pose(x_center + 0.75 * i, y, side * 0.5 * math.pi))

    x_mid_ego = float(s_ego[n // 2])

    def oncoming(category: str, x_mid: float) -> None:
        """A vehicle in the oncoming lane that passes ``x_mid`` at mid-scene."""
        size = sample_size(category, rng, ridden=True)
        model = make_object(category, size, rng, ridden=True)
        v = speed_profile(rng, n, rng.uniform(4.0, 9.0), 0.0)
        s = cumdist(v)
        x0 = x_mid + s[n // 2]
        add_agent(category, model, lane_path(s, x0, 0.5 * lane_w, -1.0, None))

    # ---- guaranteed targets: every required category is in view around mid-scene.
    ahead = x_mid_ego + rng.uniform(12.0, 18.0)
    n_guaranteed = [0]
    # The bicycle rack and the pedestrian first: each keeps a stretch of parking lane before it
    # free (a parked van, truck or bus there -- often the guaranteed one -- would hide the
    # target behind it for the whole scene), and the guaranteed vehicles then park around them.
    # Parked vehicle targets from low to tall, so the nearest spots (seen first) go to the low
    # ones and a parked bus does not stand in front of them.
    first = {"Bicycle": 0, "Pedestrian": 1, "Motorcycle": 2, "Car": 3, "Van": 4, "Truck": 5}
    required = sorted(config.required, key=lambda c: first.get(c, 6))
    n_oncoming = 0
    for cat in required:
        if cat in ("Car", "Van", "Truck", "Bus", "Motorcycle"):
            # The free parking spot nearest to ~10 m ahead of the ego at mid-scene, on either
            # side within 40 m; when the street has none there (cross street, the bicycle rack,
            # long vehicles), an oncoming vehicle. (A parked target much farther ahead would be
            # seen only along the parking lane, behind the other parked vehicles.)
            offsets = np.arange(-6.0, 40.0, 1.0)
            order = np.argsort(np.abs(offsets - 10.0) + rng.uniform(0, 6.0, len(offsets)))
            placed = False
            for k in order:
                side = -1.0 if (not park_l or rng.random() < 0.6) else 1.0
                # A low motorcycle parked across the lane needs the lane before it free.
                clear = _RACK_VIEW_M / 2 if cat == "Motorcycle" else 0.0
                if park(cat, side, ahead + offsets[k], clear_before=clear):
                    placed = True
                    break
            if not placed:
                # Staggered, so that two oncoming targets do not drive in a queue (the first
                # would hide the second).
                oncoming(cat, ahead + 12.0 * n_oncoming + rng.uniform(0.0, 12.0))
                n_oncoming += 1
        elif cat == "Pedestrian":
            pedestrian(-1.0, ahead + rng.uniform(0.0, 15.0), standing=False)
            # Its line of sight around mid-scene crosses the parking lane up to ~15 m before it.
            xs = agents[-1].pose[max(0, n // 2 - 15) : n // 2 + 15, 0]
            park_slots[-1.0].append((float(xs.min()) - _RACK_VIEW_M, float(xs.max()) + 2.0))
        elif cat == "Cyclist":
            # Alongside only in longer scenes: it must still be labelled for a while.
            slow_ego = 0.5 < float(np.mean(v_ego)) < 6.5 and n >= 60
            cyclist(
                "Cyclist",
                -1.0,
                ahead + rng.uniform(0.0, 15.0),
                rng.uniform(3.0, 6.0),
                alongside=(slow_ego and rng.random() < 0.7)
                if plan is None
                else plan.cyclist_alongside(),
            )
        elif cat == "Bicycle":
            bike_rack(
                -1.0 if rng.random() < 0.7 else 1.0,
                ahead + rng.uniform(0.0, 20.0),
                int(rng.integers(1, 4)),
                clear_before=_RACK_VIEW_M,
            )

    n_guaranteed[0] = len(agents)

    # ---- random traffic and people.
    parked_weights = {"Car": 0.78, "Van": 0.12, "Truck": 0.03, "Bus": 0.01, "Motorcycle": 0.06}
    for side in (-1.0, 1.0):
        x = x_min
        while x < x_max:
            x += rng.uniform(4.0, 9.0) / max(dens, 0.05) ** 0.5
            if rng.random() < min(0.75 * dens, 0.95):
                cat = str(rng.choice(list(parked_weights), p=list(parked_weights.values())))
                park(cat, side, x)
                x += 4.0
    moving_weights = {"Car": 0.72, "Van": 0.12, "Truck": 0.06, "Bus": 0.04, "Motorcycle": 0.06}
    for direction in (1.0, -1.0):
        for lane in range(n_lanes):
            y = -direction * (lane + 0.5) * lane_w
            ego_lane_flow = direction > 0 and abs(y - ego_lane) < 0.1
            if ego_lane_flow:
                v = v_ego
            drifting = direction > 0 and not ego_lane_flow and not standing
            drifting = drifting and rng.random() < 0.6
            if ego_lane_flow:
                v = v_ego
            elif drifting:
                # The neighbouring lane drives alongside the ego, drifting slowly back and forth
                # relative to it, its first car starting beside the ego at the edge of the
                # labelled field of view: it leaves and re-enters the view, as in real drives.
                v = np.maximum(v_ego + drift(rng, n), 0.0)
            else:
                v = speed_profile(rng, n, rng.uniform(5.0, 13.0), 0.05)
                if plan is not None:
                    v = plan.traffic_speed(n)
            s = cumdist(v)
            # Vehicles queue along the lane with gaps; the flow covers the visible stretch.
            if ego_lane_flow:
                pos = x_min if standing else float(ego[0, 0]) + rng.uniform(8.0, 25.0)
            elif drifting:
                boundary = float(ego[0, 0]) + abs(y - ego_lane) / math.tan(FOV_HALF_ANGLE)
                pos = boundary - 2.0 + rng.uniform(-1.0, 2.0)
            else:
                pos = (x_min - s[-1]) if direction > 0 else x_min
            first = True
            end = x_max if direction > 0 else x_max + s[-1]
            while pos < end:
                cat = str(rng.choice(list(moving_weights), p=list(moving_weights.values())))
                size = sample_size(cat, rng, ridden=True)
                model = make_object(cat, size, rng, ridden=True)
                front = pos + size[0]
                x_c = front - size[0] / 2
                if standing and ego_lane_flow and abs(x_c - ego[0, 0]) < size[0] / 2 + 4.0:
                    pos = front + 2.0
                    continue
                turn = None
                # Right turns into the cross street leave from the outermost lane.
                turn_lane = lane == n_lanes - 1
                if has_cross and turn_lane and not ego_lane_flow and rng.random() < 0.3:
                    r = rng.uniform(6.0, 9.0)
                    turn = (direction * cross_x - lane_w * 0.5, r)
                x_start = x_c if direction > 0 else -x_c
                pose = lane_path(s, direction * x_start, y, direction, turn)
                if plan is not None and turn is None:
                    pose = plan.weave_pose(pose, s)
                if (drifting and first) or rng.random() < min(1.0, 0.8 * dens):
                    add_agent(cat, model, pose)
                first = False
                gap = rng.uniform(6.0, 40.0) / max(dens, 0.05)
                pos = front + gap
    for side in (-1.0, 1.0):
        for _ in range(int(rng.poisson(1.5 * dens))):
            cat = "Cyclist" if rng.random() < 0.7 else "Bicycle"
            x_mid, v_mean = rng.uniform(x_min, x_max), rng.uniform(3.0, 7.0)
            cyclist(cat, side, x_mid, v_mean if plan is None else plan.cyclist_speed(v_mean))
        ped_factor = 1.0 if plan is None else plan.pedestrian_factor
        for _ in range(int(rng.poisson(6.0 * dens * ped_factor))):
            standing_share = 0.25 if plan is None else plan.standing_share
            pedestrian(side, rng.uniform(x_min + 20, x_max), rng.random() < standing_share)
        for _ in range(int(rng.poisson(0.8 * dens))):
            bike_rack(side, rng.uniform(x_min, x_max), int(rng.integers(1, 5)))

    agents = _remove_overlaps(agents, n_guaranteed[0])
    static_parts = Parts.concat(st.parts)
    return Scene(
        scene_id=int(scene_id),
        n_frames=n,
        ground=ground,
        ego=ego,
        static_bounds=np.array(st.bounds).reshape(-1, 7),
        static_solid=np.array(st.solid, dtype=bool),
        static_refl=np.array(st.refl, dtype=_F),
        static_parts=static_parts,
        agents=agents,
    )


def _footprints_overlap(pose_a, size_a, pose_b, size_b) -> np.ndarray:
    """Separating-axis test of oriented footprints per frame: poses ``(..., T, 3)`` (x, y,
    yaw), sizes ``(..., 3)``; ``True`` where the rectangles (shrunk 5 %) intersect."""
    d = pose_b[..., :2] - pose_a[..., :2]
    axes = []
    for pose in (pose_a, pose_b):
        c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
        axes += [np.stack([c, s], -1), np.stack([-s, c], -1)]
    ua, va, ub, vb = axes
    half_a = 0.475 * np.asarray(size_a)[..., None, :2]
    half_b = 0.475 * np.asarray(size_b)[..., None, :2]
    overlap = np.ones(d.shape[:-1], dtype=bool)
    for ax in axes:
        ra = half_a[..., 0] * np.abs((ua * ax).sum(-1)) + half_a[..., 1] * np.abs((va * ax).sum(-1))
        rb = half_b[..., 0] * np.abs((ub * ax).sum(-1)) + half_b[..., 1] * np.abs((vb * ax).sum(-1))
        overlap &= np.abs((d * ax).sum(-1)) <= ra + rb
    return overlap


def _remove_overlaps(agents: list[Agent], n_protected: int) -> list[Agent]:
    """Drop agents whose footprint would overlap another's in some frame (independent speed
    profiles, a cyclist at a turning car, a pedestrian meeting a parked bicycle...). The earlier
    agent wins; the first ``n_protected`` (the guaranteed targets) are never dropped. Two static
    agents are never in conflict (parked rows and racks are collision-free by construction).
    Track ids are renumbered densely afterwards, keeping the order."""
    if len(agents) < 2:
        return agents
    pose = np.stack([a.pose for a in agents])  # (A, T, 3)
    size = np.stack([a.model.size for a in agents])  # (A, 3)
    moving = np.array([np.ptp(a.pose[:, 0]) + np.ptp(a.pose[:, 1]) > 1e-6 for a in agents])
    keep = np.ones(len(agents), dtype=bool)
    for j in range(n_protected, len(agents)):
        prev = np.flatnonzero(keep[:j])
        prev = prev[moving[prev] | moving[j]]
        if not len(prev):
            continue
        # Cheap circle pre-check, then the exact rectangle test for the close ones.
        reach = 0.5 * (np.hypot(size[prev, 0], size[prev, 1]) + math.hypot(*size[j, :2]))
        dist = np.linalg.norm(pose[prev, :, :2] - pose[j, None, :, :2], axis=-1).min(axis=1)
        close = prev[dist < reach]
        if (
            len(close)
            and _footprints_overlap(pose[close], size[close], pose[j][None], size[j][None]).any()
        ):
            keep[j] = False
    out = [a for a, k in zip(agents, keep, strict=True) if k]
    for i, a in enumerate(out):
        a.track_id = i
    return out
