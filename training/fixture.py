"""The fixture of one episode (an open box or a shelf board, maybe on a table), as drawn from
the spec.

A scene spec gives the fixture's kind and ranges (footprint, heights, pose, table); each
episode draws one concrete fixture (``Fixture``, an open box, or ``Board``), records it in its
simulation result, and every later stage (geometry, discovery, rendering, hard cases)
rebuilds it from that record, so physics, labels and measurements can never disagree about
the geometry.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from task_outcome_ros.labels import BACKGROUND, FIXTURE
from training.config import SceneConfig

Vec3 = tuple[float, float, float]
Box = tuple[Vec3, Vec3]   # an upright box: half extents, centre
# A fixture's solid: half extents, centre, and its turn in the fixture's frame as x-y-z Euler
# angles (rad, pybullet's convention); upright solids carry NO_TURN.
PosedBox = tuple[Vec3, Vec3, Vec3]
NO_TURN: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Table:
    """A static table top: half extents of its top, its centre (x, y), top and room floor."""

    half_x: float
    half_y: float
    x: float
    y: float
    top_z: float
    floor_z: float

    def box(self) -> Box:
        """The table as one solid box from the room floor to its top (world frame)."""
        half_z = (self.top_z - self.floor_z) / 2
        return (self.half_x, self.half_y, half_z), (self.x, self.y, self.floor_z + half_z)


@dataclass(frozen=True)
class Region:
    """The target region of a task in its fixture's frame: where a successful placement ends.

    A box: footprint half extents, bottom and top heights above the fixture's base, and the
    thickness of the fixture's edge around the footprint (an open box's wall, a board's own
    thickness), the unit discovery measures "beyond the edge" in. An open box whose walls
    lean out widens with height (``flare``: the walls' outward run per unit of rise, its
    footprint ``half_x``, ``half_y`` at the base), and a lip widens its edge above the rim."""

    half_x: float
    half_y: float
    bottom: float
    top: float
    edge: float
    flare: float = 0.0
    lip: float = 0.0

    def half_at(self, z) -> np.ndarray:
        """The footprint's half extents (..., 2) at height(s) ``z`` above the base."""
        rise = np.clip(np.asarray(z, dtype=np.float64), 0.0, self.top)[..., None]
        return np.array([self.half_x, self.half_y]) + self.flare * rise

    def edge_at(self, z) -> np.ndarray:
        """The edge's thickness at height(s) ``z``: the lip counts only at and above the rim,
        where an object can rest on it; below, an object beside the wall is outside."""
        z = np.asarray(z, dtype=np.float64)
        return self.edge + np.where(z >= self.top, self.lip, 0.0)


@dataclass(frozen=True, kw_only=True)
class PlacedFixture:
    """What every fixture kind shares: its pose on the support, the support's tilt, a table."""

    x: float                 # m, base centre in the world
    y: float
    yaw: float               # rad, about z
    base_z: float            # m, the support plane the fixture stands on
    table: Table | None = None
    # The support's tilt from level: this many degrees, about a horizontal axis at this
    # azimuth. Simulation and geometry work in the support's frame (z normal to it), so a tilt
    # is gravity leaning in that frame, and cameras, placed against the true vertical, see
    # the whole scene tilted.
    tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 0.0

    kind = "fixture"

    def tilt_rotation(self) -> np.ndarray:
        """Support frame -> true (gravity-aligned) frame: the tilt about its horizontal axis."""
        az = math.radians(self.tilt_azimuth_deg)
        return axis_angle_rotation(np.array([math.cos(az), math.sin(az), 0.0]),
                                   math.radians(self.tilt_deg))

    def gravity(self) -> list[float]:
        """Gravity in the support's frame (the simulation's)."""
        return [float(v) for v in self.tilt_rotation().T @ np.array([0.0, 0.0, -9.81])]

    @property
    def room_floor_z(self) -> float:
        """The lowest plane of the scene: the room floor (below the table, if there is one)."""
        return self.base_z if self.table is None else self.table.floor_z

    @property
    def rotation(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> the fixture frame (origin at its base centre)."""
        c, s = np.cos(-self.yaw), np.sin(-self.yaw)
        p = np.asarray(points, dtype=np.float64) - np.array([self.x, self.y, self.base_z])
        return np.stack([c * p[..., 0] - s * p[..., 1], s * p[..., 0] + c * p[..., 1],
                         p[..., 2]], -1)

    def to_world_xy(self, offsets: np.ndarray, frame: str = "fixture") -> np.ndarray:
        """(n, 2) horizontal offsets from the footprint's centre -> world x, y. ``frame``
        "fixture": offsets along the fixture's axes; "world": along the world axes."""
        offsets = np.asarray(offsets, dtype=np.float64)
        if frame == "fixture" and self.yaw != 0.0:
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            offsets = offsets @ np.array([[c, s], [-s, c]])
        if self.x or self.y:
            offsets = offsets + np.array([self.x, self.y])
        return offsets

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """A fixture-frame point -> world."""
        return self.rotation @ np.asarray(local, float) + np.array([self.x, self.y, self.base_z])

    def centre(self) -> np.ndarray:
        """The world point cameras aim at (``aim_point`` in the fixture's frame)."""
        return self.to_world(self.aim_point())

    def aim_point(self) -> np.ndarray:
        raise NotImplementedError

    def region(self) -> Region:
        raise NotImplementedError

    def solid_boxes(self) -> list[PosedBox]:
        """The fixture's own solids (label: fixture), in its frame, base at z = 0."""
        raise NotImplementedError

    def background_boxes(self) -> list[PosedBox]:
        """Static solids that belong to the room (label: background), in the fixture's frame."""
        return []

    def labelled_boxes(self) -> list[tuple[int, PosedBox]]:
        """Every static solid with its pixel label: the fixture's, then the room's."""
        return ([(FIXTURE, box) for box in self.solid_boxes()]
                + [(BACKGROUND, box) for box in self.background_boxes()])

    def shape_key(self) -> tuple:
        """What the collision shapes depend on (not the pose, which is set per episode)."""
        table = None if self.table is None else (self.table.half_x, self.table.half_y,
                                                 self.table.top_z - self.table.floor_z)
        return (self.kind, tuple(self.solid_boxes()), tuple(self.background_boxes()), table)

    def outer_half_footprint(self) -> np.ndarray:
        """Half the fixture's outer footprint along its x and y, from its own solids."""
        reach = np.zeros(2)
        for half, centre, turn in self.solid_boxes():
            spread = np.abs(euler_rotation(turn)) @ np.asarray(half)
            reach = np.maximum(reach, np.abs(np.asarray(centre[:2])) + spread[:2])
        return reach

    def to_record(self) -> dict:
        return {**asdict(self), "kind": self.kind}


# A plain open box's record leaves out the wall-shape fields it does not use, so records of
# specs without them stay what they were (fixture_from_record fills the defaults back in).
PLAIN_WALLS = {"flare_deg": 0.0, "lip_width": 0.0, "handle_holes": False}


# A handle hole in each x wall: the box's ends when its x side is the longer, which the tote
# spec's independent draws of the two sides make about three totes in four (the others carry
# their holes in the long sides, as some crates do). The hole is HANDLE_WIDTH wide or half
# the wall's inner length, whichever is smaller, this tall, its top this far below the rim
# along the wall; walls too short to keep that much wall below it have none.
HANDLE_WIDTH = 0.12     # m
HANDLE_HEIGHT = 0.035   # m
HANDLE_DROP = 0.025     # m
HANDLE_MIN_WALL = HANDLE_DROP + HANDLE_HEIGHT + 0.03   # m of wall, along its slope
FIN_MAX = 0.01          # m: how far a leaning wall's strip may reach past the next wall
SLIVER = 0.005          # m: no strip of a wall is thinner than this


@dataclass(frozen=True, kw_only=True)
class Fixture(PlacedFixture):
    """An open-top box with a rectangular inner footprint (``fixture: open_box``): its target
    region is the inner volume, up to the walls' top. Its walls may lean out by ``flare_deg``
    (hinged at the inner footprint's edge, so the opening widens with height), a flat lip may
    run round the rim ``lip_width`` beyond them, and its x walls may have handle holes."""

    half_x: float            # m, inner half extents at the base
    half_y: float
    wall_height: float       # m, base to the walls' top
    wall_thickness: float
    bottom_thickness: float
    flare_deg: float = 0.0
    lip_width: float = 0.0
    handle_holes: bool = False   # holes wanted: walls shorter than HANDLE_MIN_WALL get none

    kind = "open_box"

    @property
    def _flare(self) -> float:
        """The walls' outward run per unit of rise."""
        return math.tan(math.radians(self.flare_deg))

    def _rim_thickness(self) -> float:
        """The wall's horizontal thickness (its thickness, seen from above when leaning)."""
        return self.wall_thickness / math.cos(math.radians(self.flare_deg))

    def to_record(self) -> dict:
        record = super().to_record()
        for field, plain in PLAIN_WALLS.items():
            if record[field] == plain:
                del record[field]
        return record

    def region(self) -> Region:
        return Region(self.half_x, self.half_y, self.bottom_thickness, self.wall_height,
                      self._rim_thickness(), flare=self._flare, lip=self.lip_width)

    def aim_point(self) -> np.ndarray:
        """Halfway up the walls over the footprint's centre."""
        return np.array([0.0, 0.0, self.wall_height / 2])

    def solid_boxes(self) -> list[PosedBox]:
        """The open box: its bottom, four walls (each in pieces round a handle hole), and a
        flat rim over their tops when they lean or carry a lip. An x wall spans the corners."""
        hx, hy, t, h = self.half_x, self.half_y, self.wall_thickness, self.wall_height
        bottom = ((hx + t, hy + t, self.bottom_thickness / 2),
                  (0.0, 0.0, self.bottom_thickness / 2), NO_TURN)
        top_x, top_y = hx + h * self._flare, hy + h * self._flare
        solids = [bottom]
        for axis, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):
            solids += self._wall(axis, sign, self.handle_holes and axis == 0)
        if self.flare_deg or self.lip_width:
            solids += self._rim(top_x, top_y)
        return solids

    def _wall(self, axis: int, sign: float, hole: bool) -> list[PosedBox]:
        """One wall leaning out by flare_deg from the inner footprint's edge. A leaning wall
        narrows towards its foot, which one box cannot: it is a stack of strips up its slope,
        each as long as the opening at its own top (an x wall also spans the corners), so a
        strip's foot reaches past the next wall by about ``FIN_MAX`` at most (a few mm more
        beside a handle hole, where a cut gave way to the hole's edge). A handle hole takes
        the middle of the strips it spans. The first strip's foot is square to the slope, so
        its outer corner dips ``t sin(flare)`` below the base (3 mm at 20 deg), into the
        support, where neither the physics (static solids do not collide) nor a camera sees
        it."""
        t, h = self.wall_thickness, self.wall_height
        lean = math.radians(self.flare_deg)
        length = h / math.cos(lean)                      # up the slope
        hinge = self.half_x if axis == 0 else self.half_y
        across = self.half_y if axis == 0 else self.half_x   # half the footprint along it
        # Unit vectors in the fixture's frame: up the slope, out through the wall, along it.
        up = np.zeros(3)
        up[axis], up[2] = sign * math.sin(lean), math.cos(lean)
        out = np.zeros(3)
        out[axis], out[2] = sign * math.cos(lean), -math.sin(lean)
        along = np.zeros(3)
        along[1 - axis] = 1.0
        # A box's x tilts about y (x walls), its y about x (y walls); upright walls untilted.
        if not self.flare_deg:
            turn = NO_TURN
        elif axis == 0:
            turn = (0.0, sign * lean, 0.0)
        else:
            turn = (-sign * lean, 0.0, 0.0)
        strips = max(1, math.ceil(h * self._flare / FIN_MAX))
        cuts = list(np.linspace(0.0, length, strips + 1))
        opening = None
        if hole and length >= HANDLE_MIN_WALL:
            opening = (length - HANDLE_DROP - HANDLE_HEIGHT, length - HANDLE_DROP)
            # The hole's edges replace strip cuts within 5 mm of them: no sliver of a strip.
            cuts = sorted({c for c in cuts if min(abs(c - e) for e in opening) > SLIVER}
                          | set(opening))
        hinge_point = np.zeros(3)
        hinge_point[axis] = sign * hinge
        width = min(HANDLE_WIDTH, self.half_y)           # the hole's
        solids = []
        for u0, u1 in zip(cuts[:-1], cuts[1:]):
            span = across + u1 * math.cos(lean) * self._flare + (t if axis == 0 else 0.0)
            in_hole = opening is not None and opening[0] <= u0 and u1 <= opening[1]
            for a0, a1 in ([(-span, -width / 2), (width / 2, span)] if in_hole
                           else [(-span, span)]):
                centre = (hinge_point + (a0 + a1) / 2 * along + (u0 + u1) / 2 * up
                          + t / 2 * out)
                half = [0.0, 0.0, (u1 - u0) / 2]
                half[axis], half[1 - axis] = t / 2, (a1 - a0) / 2
                solids.append((tuple(half), tuple(float(v) for v in centre), turn))
        return solids

    def _rim(self, top_x: float, top_y: float) -> list[PosedBox]:
        """A flat rim, a wall's thickness deep, from the opening's edge to the lip's: the x
        sides span the corners."""
        t, h = self.wall_thickness, self.wall_height
        width = self._rim_thickness() + self.lip_width
        z = h - t / 2
        return [((width / 2, top_y + width, t / 2), (sign * (top_x + width / 2), 0.0, z), NO_TURN)
                for sign in (1.0, -1.0)] + [
                ((top_x, width / 2, t / 2), (0.0, sign * (top_y + width / 2), z), NO_TURN)
                for sign in (1.0, -1.0)]


# A board's legs and the wall behind it (see Board).
LEG_WIDTH = 0.04             # m, square legs
BACK_WALL = (3.0, 0.05, 2.5)  # m: width, thickness, height of the room wall a board may hang on


@dataclass(frozen=True, kw_only=True)
class Board(PlacedFixture):
    """A shelf board (``fixture: board``): a slab whose top is ``height`` above the support,
    standing on four legs or fixed to a wall behind it (``wall_mounted``). Its front edge is
    the -y side. The target region is the volume above the board, ``clearance`` high."""

    half_x: float            # m, half the board's width (x) and depth (y)
    half_y: float
    height: float            # m, support to the board's top
    thickness: float
    clearance: float         # m, height of the region above the board
    wall_mounted: bool = False

    kind = "board"

    def region(self) -> Region:
        return Region(self.half_x, self.half_y, self.height, self.height + self.clearance,
                      self.thickness)

    def aim_point(self) -> np.ndarray:
        """Over the front edge, 0.6 of the way up to the board: the board's top, what stands
        on it and the floor in front of it (where objects fall) all stay in view."""
        return np.array([0.0, -self.half_y, 0.6 * self.height])

    def solid_boxes(self) -> list[PosedBox]:
        t, h = self.thickness, self.height
        board = ((self.half_x, self.half_y, t / 2), (0.0, 0.0, h - t / 2), NO_TURN)
        if self.wall_mounted:
            return [board]
        leg_half = ((LEG_WIDTH / 2, LEG_WIDTH / 2, (h - t) / 2))
        inset = LEG_WIDTH / 2
        legs = [(leg_half, (sx * (self.half_x - inset), sy * (self.half_y - inset), (h - t) / 2),
                 NO_TURN) for sx in (-1, 1) for sy in (-1, 1)]
        return [board, *legs]

    def background_boxes(self) -> list[PosedBox]:
        if not self.wall_mounted:
            return []
        width, thick, tall = BACK_WALL
        return [((width / 2, thick / 2, tall / 2), (0.0, self.half_y + thick / 2, tall / 2),
                 NO_TURN)]


FIXTURE_KINDS = {"open_box": Fixture, "board": Board}   # by SceneConfig.fixture (FIXTURES)


def euler_rotation(turn: Vec3) -> np.ndarray:
    """The rotation of x-y-z Euler angles (rad) as pybullet reads them: R = Rz Ry Rx."""
    if tuple(turn) == NO_TURN:
        return np.eye(3)
    (cx, cy, cz), (sx, sy, sz) = np.cos(turn), np.sin(turn)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def axis_angle_rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues' formula)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                  [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


def fixture_from_record(record: dict) -> PlacedFixture:
    """The fixture an episode recorded (records without a kind are open boxes)."""
    record = dict(record)
    kind = record.pop("kind", "open_box")
    if kind not in FIXTURE_KINDS:
        raise ValueError(f"fixture record of unknown kind {kind!r}; known: "
                         f"{sorted(FIXTURE_KINDS)}")
    table = record.get("table")
    return FIXTURE_KINDS[kind](**{**record, "table": Table(**table) if table else None})


def episode_fixture(episode: dict, scene: SceneConfig) -> PlacedFixture:
    """The fixture an episode was simulated with. Episodes simulated before fixtures were
    recorded had the spec's one square open box at the origin."""
    if "fixture" in episode:
        return fixture_from_record(episode["fixture"])
    return first_fixture(scene, float(episode["container_yaw"]), float(episode["floor_z"]))


def first_fixture(scene: SceneConfig, yaw: float = 0.0, base_z: float = 0.0) -> PlacedFixture:
    """The spec's fixture at the low end of every range, at the origin (nothing drawn)."""
    if scene.fixture == "board":
        return Board(half_x=scene.board_width[0] / 2, half_y=scene.board_depth[0] / 2,
                     height=scene.board_height[0], thickness=scene.board_thickness,
                     clearance=scene.clearance, x=0.0, y=0.0, yaw=yaw, base_z=base_z)
    return Fixture(half_x=scene.inner_size_x[0] / 2, half_y=scene.inner_size_y[0] / 2,
                   wall_height=scene.wall_height[0], wall_thickness=scene.wall_thickness,
                   bottom_thickness=scene.bottom_thickness, flare_deg=scene.wall_flare_deg[0],
                   lip_width=scene.lip_width[0], x=0.0, y=0.0, yaw=yaw, base_z=base_z)


def _uniform(rng: np.random.Generator, interval: tuple[float, float]) -> float:
    """A draw from [lo, hi]; a fixed value (lo == hi) consumes no randomness."""
    lo, hi = interval
    return float(lo) if lo == hi else float(rng.uniform(lo, hi))


def draw_fixture(scene: SceneConfig, yaw: float, base_z: float,
                 rng: np.random.Generator) -> PlacedFixture:
    """The episode's fixture: its geometry and position from ``rng`` (its own stream), yaw and
    support height as the episode drew them."""
    if scene.fixture == "board":
        geometry = {"half_x": _uniform(rng, scene.board_width) / 2,
                    "half_y": _uniform(rng, scene.board_depth) / 2,
                    "height": _uniform(rng, scene.board_height),
                    "thickness": scene.board_thickness, "clearance": scene.clearance,
                    "wall_mounted": bool(rng.random() < scene.wall_mounted_share)}
    else:
        geometry = {"half_x": _uniform(rng, scene.inner_size_x) / 2,
                    "half_y": _uniform(rng, scene.inner_size_y) / 2,
                    "wall_height": _uniform(rng, scene.wall_height),
                    "wall_thickness": scene.wall_thickness,
                    "bottom_thickness": scene.bottom_thickness}
        # Fixed or absent in older specs, where these consume no randomness.
        geometry["flare_deg"] = _uniform(rng, scene.wall_flare_deg)
        geometry["lip_width"] = _uniform(rng, scene.lip_width)
        geometry["handle_holes"] = bool(scene.handle_hole_share > 0
                                        and rng.random() < scene.handle_hole_share)
        if scene.plain_wall_share > 0 and rng.random() < scene.plain_wall_share:
            geometry.update(PLAIN_WALLS)
    offset = scene.fixture_offset
    x, y = (float(v) for v in rng.uniform(-offset, offset, 2)) if offset > 0 else (0.0, 0.0)
    table = None
    if scene.table_size is not None:
        table = _draw_table(scene, geometry, x, y, yaw, base_z, rng)
    tilt, tilt_azimuth = 0.0, 0.0
    if scene.support_tilt_deg[1] > 0:
        tilt = _uniform(rng, scene.support_tilt_deg)
        tilt_azimuth = float(rng.uniform(0.0, 360.0))
    return FIXTURE_KINDS[scene.fixture](**geometry, x=x, y=y, yaw=yaw, base_z=base_z,
                                        table=table, tilt_deg=tilt,
                                        tilt_azimuth_deg=tilt_azimuth)


def _outer_half(scene: SceneConfig, geometry: dict, key: str) -> float:
    """The drawn fixture's outer half footprint along one axis (``key``: half_x or half_y)."""
    if scene.fixture == "board":
        return geometry[key]
    if not (geometry["flare_deg"] or geometry["lip_width"]):
        return geometry[key] + scene.wall_thickness
    # Leaning walls and a lip: the opening at the rim plus the rim's width, as the box's own
    # region gives them (placed anywhere: only its shape matters here).
    region = Fixture(**geometry, x=0.0, y=0.0, yaw=0.0, base_z=0.0).region()
    axis = 0 if key == "half_x" else 1
    return float(region.half_at(region.top)[axis] + region.edge_at(region.top))


def _draw_table(scene: SceneConfig, geometry: dict, x: float, y: float, yaw: float,
                base_z: float, rng: np.random.Generator) -> Table:
    """The table under the episode's fixture (base centre x, y): its size and height, and
    where the fixture stands on it: within +-``table_offset`` of its centre along the world
    axes, or with ``table_edge_margin`` anywhere along the fixture's axes that keeps its outer
    footprint that far inside the table's edges."""
    half_x, half_y = (_uniform(rng, side) / 2 for side in scene.table_size)
    # The spec's table sizes fit its largest upright-walled box (SceneConfig validates that);
    # a box whose walls lean out or carry a lip reaches farther, and a table drawn too small
    # for it grows to fit. For upright walls this never changes a draw.
    reach = (scene.table_edge_margin if scene.table_edge_margin is not None
             else math.sqrt(2.0) * scene.table_offset)
    half_x = max(half_x, _outer_half(scene, geometry, "half_x") + reach)
    half_y = max(half_y, _outer_half(scene, geometry, "half_y") + reach)
    height = _uniform(rng, scene.table_height)
    if scene.table_edge_margin is None:
        toff = scene.table_offset
        tx, ty = (float(v) for v in rng.uniform(-toff, toff, 2)) if toff > 0 else (0.0, 0.0)
    else:
        free = [max(0.0, half - _outer_half(scene, geometry, key) - scene.table_edge_margin)
                for half, key in ((half_x, "half_x"), (half_y, "half_y"))]
        along_x, along_y = (float(rng.uniform(-f, f)) if f > 0 else 0.0 for f in free)
        c, s = math.cos(yaw), math.sin(yaw)   # the fixture's axes in the world
        tx, ty = c * along_x - s * along_y, s * along_x + c * along_y
    return Table(half_x, half_y, x + tx, y + ty, base_z, base_z - height)
