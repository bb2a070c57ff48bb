"""Frozen, validated configs, one per stage. Defaults: the nominal scene, docs/interface.md §1, §4.

Every run saves the resolved configs (``config.json`` in the run folder) and every checkpoint
embeds them, so a run can be reproduced from its own files.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


class ConfigError(ValueError):
    """A config value outside its allowed range; the message names the field and the range."""


def _check_range(owner: str, name: str, value: float, lo: float, hi: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{owner}.{name} = {value!r} is outside the allowed range [{lo}, {hi}]")


def _check_int(owner: str, name: str, value: int, lo: int, hi: int) -> None:
    """Counts must be real integers (a 10.5-episode run would crash later, far from here)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{owner}.{name} = {value!r} must be a whole number in [{lo}, {hi}]")
    _check_range(owner, name, value, lo, hi)


def _check_interval(owner: str, name: str, interval: tuple[float, float], lo: float,
                    hi: float) -> None:
    if not isinstance(interval, (tuple, list)) or len(interval) != 2:
        raise ConfigError(f"{owner}.{name} must be a (min, max) pair, got {interval!r}")
    a, b = interval
    _check_range(owner, f"{name}[0]", a, lo, hi)
    _check_range(owner, f"{name}[1]", b, lo, hi)
    if a > b:
        raise ConfigError(f"{owner}.{name} = {interval!r}: min must not exceed max")


SHAPES = ("box", "cylinder")
FIXTURES = ("open_box", "board")   # training/fixture.py FIXTURE_KINDS
# How discovery describes a cluster, in its target region's terms (training/discover.py).
DESCRIPTORS = ("inside", "outside", "partly_inside")
# Not outcome or fixture names: class 0, and the keys reports put beside the outcomes'.
RESERVED_WORDS = ("background", "image_all_correct", "presence_precision", "presence_recall",
                  "pixel_miou", "iou", "n_images", "mistakes", "confusion")
# Validation episodes per robustness stress point (training/robustness.py): 300 keeps the 95 %
# interval around 0.97 at 0.94-0.98 (100 gave 0.92-0.99, wider than most gaps worth judging).
ROBUSTNESS_IMAGES = 300
NOISE_MODELS = ("kinect_v1",)   # noise: structured light; tof and stereo: the other two


@dataclass(frozen=True)
class SceneConfig:
    """The simulated place task (docs/interface.md §1) and its physics domain randomisation.

    Every range is drawn per episode (uniform); a range with min == max is a fixed value. The
    fixture (``fixture``) is an open-top box with a rectangular inner footprint (``open_box``)
    or a shelf board (``board``), standing on a support plane: the room floor, or the top of a
    table with the room floor below it. Its target region (training/fixture.py ``Region``) is
    where a successful placement ends: the open box's inner volume, the volume above a board.
    """

    fixture: str = "open_box"             # one of FIXTURES
    # An open box, in its own frame: x and y along its walls, z up from its base.
    inner_size_x: tuple[float, float] = (1.0, 1.0)    # m, inner footprint along x
    inner_size_y: tuple[float, float] = (1.0, 1.0)    # m, inner footprint along y
    wall_height: tuple[float, float] = (0.25, 0.25)   # m, base to rim top
    wall_thickness: float = 0.02          # m
    bottom_thickness: float = 0.02        # m, the box's floor slab
    # Real totes and trays are not five flat slabs: their walls lean outwards (a few degrees
    # of draft on a tote, far more on a tray), a lip runs round the rim, and the short ends
    # have handle holes. Each is drawn per episode (fixture.py ``Fixture``); the defaults
    # leave the box as it was. The walls' slope from vertical (deg, top outwards), the lip's
    # width beyond the walls (m), and the share of boxes with a handle hole in each x wall.
    # ``plain_wall_share`` of the boxes get none of the three (upright walls, no lip, no
    # holes: the box of a spec without them), so that ranges drawn uniformly still cover
    # plain boxes, which many real crates are, and not one box in a hundred.
    wall_flare_deg: tuple[float, float] = (0.0, 0.0)
    lip_width: tuple[float, float] = (0.0, 0.0)
    handle_hole_share: float = 0.0
    plain_wall_share: float = 0.0
    # A board: width (x) and depth (y) of its top, its top's height above the support, its
    # thickness, the height of the region above it, and the share of episodes in which it hangs
    # on a wall behind it instead of standing on four legs. Its front edge is its -y side.
    board_width: tuple[float, float] = (0.9, 0.9)           # m
    board_depth: tuple[float, float] = (0.35, 0.35)         # m
    board_height: tuple[float, float] = (0.8, 0.8)          # m
    board_thickness: float = 0.025        # m
    clearance: float = 0.4                # m
    wall_mounted_share: float = 0.5
    # Either kind's pose.
    fixture_offset: float = 0.0           # m, base centre uniform in +-this along x and y
    fixture_yaw_deg: tuple[float, float] = (-45.0, 45.0)     # a square repeats every 90 deg
    # The support plane's height (the room floor, or the table top), and an optional table.
    floor_height: tuple[float, float] = (-0.05, 0.05)        # m
    # The table top's size along the fixture's x and y, each a (min, max) range drawn per
    # episode (a spec may give a fixed (x, y) pair). The table turns with the fixture.
    table_size: tuple[tuple[float, float], tuple[float, float]] | None = None   # m
    table_height: tuple[float, float] = (0.75, 0.75)         # m, table top above the room floor
    table_offset: float = 0.0             # m, table centre uniform in +-this from the fixture
    # Instead of table_offset: the fixture stands anywhere on the drawn table, its outer
    # footprint at least this far inside the table's edges (m), as totes stand at a bench's
    # edge as often as at its middle. None keeps table_offset.
    table_edge_margin: float | None = None
    # The support's tilt from level (deg), towards a uniformly drawn direction: real floors
    # and tables are rarely level, and cameras are placed against the true vertical.
    support_tilt_deg: tuple[float, float] = (0.0, 0.0)
    # The objects.
    min_objects: int = 1
    max_objects: int = 4
    # The share of episodes in which nothing was placed: the fixture and its scenery as
    # drawn, no object (a cell before the place, or after the gripper lost its object out of
    # view). Drawn from a stream of its own, so the other episodes are simulated as a spec
    # without it simulates them. The bundled specs leave it at 0: on the tote task 5 % of
    # empty scenes changed nothing a model says of empty containers, simulated or real
    # (docs/experiments.md).
    empty_share: float = 0.0
    shape_weights: tuple[tuple[str, float], ...] = (("box", 1.0),)
    object_edge: tuple[float, float] = (0.08, 0.30)          # m, box edges, per axis
    cylinder_diameter: tuple[float, float] = (0.06, 0.20)    # m
    cylinder_height: tuple[float, float] = (0.06, 0.25)      # m
    object_mass: tuple[float, float] = (0.1, 2.0)            # kg
    friction: tuple[float, float] = (0.3, 1.0)
    restitution: tuple[float, float] = (0.0, 0.4)
    # Bullet's rolling friction (m) of the objects; 0 leaves it off. Without it a cylinder on
    # its side rolls on over a level floor until the episode's time runs out.
    rolling_friction: float = 0.0
    # The release. "drop": object centres ``release_height`` above the region's top, over an
    # area reaching ``release_margin`` beyond its footprint on every side (negative: strictly
    # inside it). "place": a gripper sets each object down over the region's front edge (-y),
    # at a depth ``place_edge_offset`` inside it (negative: beyond it) and anywhere along it
    # ``release_margin`` from its ends, its lowest point ``place_gap`` above the region's
    # bottom, upright but for a ``place_tilt_deg`` pose error.
    release_mode: str = "drop"
    release_height: tuple[float, float] = (1.5, 1.5)         # m
    release_margin: float = 0.1           # m
    # Axes of that area: "fixture" (along the fixture's axes) or "world" (the paper's scene:
    # a square area fixed in the world while the fixture's yaw varies).
    release_frame: str = "world"
    release_orientation: str = "random"   # random | upright (random yaw, object z up)
    place_edge_offset: tuple[float, float] = (-0.05, 0.10)   # m
    place_gap: tuple[float, float] = (0.0, 0.05)             # m
    place_tilt_deg: tuple[float, float] = (0.0, 0.0)
    # Scenery nobody placed, drawn per frame at render time (training/scenery.py) from a stream
    # of its own, so a spec without it renders what it did before: in ``neighbour_share`` of
    # the frames, ``neighbour_count`` copies of the episode's open box stand beside it, each on
    # one of its four sides (a row, or a corner of one) at its base height, on the table or
    # past its edge as on a rack, ``neighbour_gap`` apart (m, outer edge to outer edge), each
    # holding ``neighbour_contents`` boxes of ``object_edge``. All of it is background: a real
    # cell's next tote and what it holds are not an outcome of this place, and without it in
    # training anything beside the fixture can only be a fallen object.
    neighbour_share: float = 0.0
    neighbour_count: tuple[int, int] = (1, 2)
    neighbour_gap: tuple[float, float] = (0.0, 0.15)
    neighbour_contents: tuple[int, int] = (0, 4)
    # Share of the frames rendered as an empty cell (render.render_episode's ``emptied``: the
    # same camera and sensor, the fixture and the objects left out, every pixel background),
    # drawn per frame from a stream of its own, so a spec without it renders what it did
    # before. Every frame of a spec without it holds its fixture, and nothing then tells a
    # model what an empty cell looks like: a default candidate labelled a quarter of an
    # empty floor as container, the tote model a bare table top as the tote
    # (docs/evaluation.md, the robustness suite's scene_emptied point). Not ``empty_share``
    # above, which places no object in a container that is still there.
    empty_cell_share: float = 0.0
    # Integration and the end of an episode.
    timestep: float = 1.0 / 240.0
    solver_iterations: int = 10
    max_episode_time: float = 8.0         # s; objects still moving then are recorded unsettled
    rest_linear_speed: float = 0.01       # m/s
    rest_angular_speed: float = 0.05      # rad/s
    rest_hold_time: float = 0.25          # s every object must stay below both speeds

    @property
    def height_scale(self) -> float:
        """The network's height unit (m): the highest top of the fixture the spec draws."""
        return float(self.board_height[1] if self.fixture == "board" else self.wall_height[1])

    @property
    def smallest_half_width(self) -> float:
        """Half the narrowest footprint the spec draws (m)."""
        sizes = ((self.board_width, self.board_depth) if self.fixture == "board"
                 else (self.inner_size_x, self.inner_size_y))
        return min(sizes[0][0], sizes[1][0]) / 2

    @property
    def shapes(self) -> dict[str, float]:
        return dict(self.shape_weights)

    def validate(self) -> SceneConfig:
        o = "scene"
        if self.fixture not in FIXTURES:
            raise ConfigError(f"{o}.fixture = {self.fixture!r}: expected one of {FIXTURES}")
        _check_interval(o, "inner_size_x", self.inner_size_x, 0.1, 5.0)
        _check_interval(o, "inner_size_y", self.inner_size_y, 0.1, 5.0)
        _check_interval(o, "wall_height", self.wall_height, 0.05, 1.0)
        _check_range(o, "wall_thickness", self.wall_thickness, 0.002, 0.2)
        _check_range(o, "bottom_thickness", self.bottom_thickness, 0.002, 0.1)
        _check_interval(o, "wall_flare_deg", self.wall_flare_deg, 0.0, 30.0)
        _check_interval(o, "lip_width", self.lip_width, 0.0, 0.1)
        _check_range(o, "handle_hole_share", self.handle_hole_share, 0.0, 1.0)
        _check_range(o, "plain_wall_share", self.plain_wall_share, 0.0, 1.0)
        if self.fixture == "board" and (self.wall_flare_deg[1] or self.lip_width[1]
                                        or self.handle_hole_share or self.plain_wall_share):
            raise ConfigError(f"{o}: wall_flare_deg, lip_width, handle_hole_share and "
                              "plain_wall_share shape an open box's walls; a board has none")
        _check_interval(o, "board_width", self.board_width, 0.1, 5.0)
        _check_interval(o, "board_depth", self.board_depth, 0.1, 5.0)
        _check_interval(o, "board_height", self.board_height, 0.05, 3.0)
        _check_range(o, "board_thickness", self.board_thickness, 0.005, 0.2)
        _check_range(o, "clearance", self.clearance, 0.05, 3.0)
        _check_range(o, "wall_mounted_share", self.wall_mounted_share, 0.0, 1.0)
        _check_range(o, "fixture_offset", self.fixture_offset, 0.0, 2.0)
        _check_interval(o, "fixture_yaw_deg", self.fixture_yaw_deg, -180.0, 180.0)
        _check_interval(o, "floor_height", self.floor_height, -1.0, 1.0)
        if self.table_size is not None:
            if not isinstance(self.table_size, (tuple, list)) or len(self.table_size) != 2:
                raise ConfigError(f"{o}.table_size must be (x, y) sizes or ((x_min, x_max), "
                                  f"(y_min, y_max)) ranges, got {self.table_size!r}")
            for axis, side in zip("xy", self.table_size):
                _check_interval(o, f"table_size.{axis}", side, 0.2, 10.0)
        _check_interval(o, "table_height", self.table_height, 0.2, 2.0)
        _check_range(o, "table_offset", self.table_offset, 0.0, 5.0)
        if self.table_edge_margin is not None:
            _check_range(o, "table_edge_margin", self.table_edge_margin, 0.0, 2.0)
            if self.table_offset:
                raise ConfigError(f"{o}: table_edge_margin places the fixture anywhere on the "
                                  f"table; leave table_offset at 0 (it is {self.table_offset})")
        _check_interval(o, "support_tilt_deg", self.support_tilt_deg, 0.0, 15.0)
        _check_int(o, "min_objects", self.min_objects, 1, 8)
        _check_int(o, "max_objects", self.max_objects, self.min_objects, 8)
        # At most half: discovery clusters the objects of the other episodes.
        _check_range(o, "empty_share", self.empty_share, 0.0, 0.5)
        _check_range(o, "empty_cell_share", self.empty_cell_share, 0.0, 0.5)  # most show it
        self._validate_shapes(o)
        _check_interval(o, "object_edge", self.object_edge, 0.01, 1.0)
        _check_interval(o, "cylinder_diameter", self.cylinder_diameter, 0.01, 1.0)
        _check_interval(o, "cylinder_height", self.cylinder_height, 0.01, 1.0)
        _check_interval(o, "object_mass", self.object_mass, 0.01, 100.0)
        _check_interval(o, "friction", self.friction, 0.0, 5.0)
        _check_interval(o, "restitution", self.restitution, 0.0, 1.0)
        _check_range(o, "rolling_friction", self.rolling_friction, 0.0, 0.1)
        if self.release_mode not in ("drop", "place"):
            raise ConfigError(f"{o}.release_mode = {self.release_mode!r}: "
                              "expected one of ('drop', 'place')")
        _check_interval(o, "release_height", self.release_height, 0.0, 5.0)
        _check_range(o, "release_margin", self.release_margin, -0.5, 3.0)
        _check_interval(o, "place_edge_offset", self.place_edge_offset, -0.5, 0.5)
        _check_interval(o, "place_gap", self.place_gap, 0.0, 0.5)
        _check_interval(o, "place_tilt_deg", self.place_tilt_deg, 0.0, 45.0)
        if self.release_frame not in ("fixture", "world"):
            raise ConfigError(f"{o}.release_frame = {self.release_frame!r}: "
                              "expected one of ('fixture', 'world')")
        if self.release_orientation not in ("random", "upright"):
            raise ConfigError(f"{o}.release_orientation = {self.release_orientation!r}: "
                              "expected one of ('random', 'upright')")
        self._validate_neighbours(o)
        _check_range(o, "timestep", self.timestep, 1e-4, 0.05)
        _check_int(o, "solver_iterations", self.solver_iterations, 1, 1000)
        _check_range(o, "max_episode_time", self.max_episode_time, 0.5, 120.0)
        if self.table_size is not None:
            self._validate_table(o)
        self._validate_kind(o)
        return self

    def _validate_kind(self, o: str) -> None:
        """What the fixture's kind and the release mode need of each other."""
        if self.fixture == "board" and self.board_height[0] <= self.board_thickness:
            raise ConfigError(f"{o}.board_height = {list(self.board_height)}: the board's top "
                              f"must stand higher than its thickness ({self.board_thickness})")
        if self.release_mode == "place" and self.fixture != "board":
            raise ConfigError(f"{o}.release_mode = 'place' sets objects down over a board's "
                              f"front edge; an {self.fixture} takes release_mode 'drop'")
        if self.release_mode == "place" and self.place_edge_offset[1] >= self.board_depth[0]:
            raise ConfigError(f"{o}.place_edge_offset = {list(self.place_edge_offset)}: the "
                              f"deepest placement must stay on the shallowest board "
                              f"(board_depth {list(self.board_depth)})")

    def _validate_neighbours(self, o: str) -> None:
        _check_range(o, "neighbour_share", self.neighbour_share, 0.0, 1.0)
        _check_interval(o, "neighbour_gap", self.neighbour_gap, 0.0, 2.0)
        for name, bounds in (("neighbour_count", (1, 4)), ("neighbour_contents", (0, 12))):
            pair = getattr(self, name)
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise ConfigError(f"{o}.{name} must be a [min, max] pair, got {pair!r}")
            for i in (0, 1):
                _check_int(o, f"{name}[{i}]", pair[i], *bounds)
            if pair[0] > pair[1]:
                raise ConfigError(f"{o}.{name} = {list(pair)}: min must not exceed max")
        if self.neighbour_share > 0 and self.fixture != "open_box":
            raise ConfigError(f"{o}.neighbour_share = {self.neighbour_share}: neighbours are "
                              f"copies of an open box beside it; a {self.fixture}'s would stand "
                              "in its wall or where objects fall")

    def _validate_shapes(self, o: str) -> None:
        names = [name for name, _ in self.shape_weights]
        unknown = sorted(set(names) - set(SHAPES))
        if unknown or len(set(names)) != len(names):
            raise ConfigError(f"{o}.shape_weights: shapes {unknown or names} must be distinct "
                              f"names from {SHAPES}")
        for name, weight in self.shape_weights:
            _check_range(o, f"shape_weights.{name}", weight, 0.0, 1000.0)
        if sum(w for _, w in self.shape_weights) <= 0:
            raise ConfigError(f"{o}.shape_weights: at least one shape needs a weight > 0")

    def outer_half(self, inner_half: float) -> float:
        """A fixture's outer half footprint from its inner one: an open box's upright wall
        stands outside its footprint, a board's edge is the footprint's own. (Leaning walls
        and a lip reach farther: the episode's table grows to fit them, fixture.py.)"""
        return inner_half + (0.0 if self.fixture == "board" else self.wall_thickness)

    def fixture_outer_half(self, axis: int) -> float:
        """Half the largest outer footprint the spec draws along the fixture's x (0) or y (1)."""
        sizes = ((self.board_width, self.board_depth) if self.fixture == "board"
                 else (self.inner_size_x, self.inner_size_y))
        return self.outer_half(sizes[axis][1] / 2)

    def _validate_table(self, o: str) -> None:
        """The fixture must stand on the table wherever its size, the table's size and their
        placement are drawn. The table turns with the fixture, so this is per axis of the
        fixture; an offset of up to ``table_offset`` on each axis reaches sqrt(2) x that."""
        reach = (self.table_edge_margin if self.table_edge_margin is not None
                 else math.sqrt(2.0) * self.table_offset)
        for k, axis in enumerate("xy"):
            need = self.fixture_outer_half(k) + reach
            half = self.table_size[k][0] / 2
            if need > half:
                raise ConfigError(
                    f"{o}.table_size = {[list(side) for side in self.table_size]}: along "
                    f"{axis} the fixture reaches {need:.3f} m from the table's centre "
                    f"(footprint, wall and table_offset or table_edge_margin) but the "
                    f"smallest table's half size is {half:.3f} m; make it at least "
                    f"{2 * need:.3f} m")


@dataclass(frozen=True)
class CameraConfig:
    """The envelope camera draws come from (docs/interface.md §4).

    The defaults are the default task's Kinect-v1-like envelope; a scene spec may set its own
    within the allowed limits below (DatasetConfig checks that it can see the fixture)."""

    width: int = 640
    height: int = 480
    focal_px: tuple[float, float] = (525.0, 590.0)    # fx = fy, at this width
    principal_offset_px: float = 8.0      # |cx - W/2|, |cy - H/2| at most this
    distance: tuple[float, float] = (1.6, 2.4)        # m, camera to look-at point
    elevation_deg: tuple[float, float] = (40.0, 65.0)  # above the horizontal; 90 = straight down
    azimuth_deg: tuple[float, float] = (0.0, 360.0)   # around the fixture, from its x axis
    roll_deg: tuple[float, float] = (0.0, 0.0)        # about the optical axis
    # "world": azimuth from the world's x axis (the paper's scene: cameras anywhere around);
    # "fixture": from the fixture's x axis, so a range can keep cameras in front of a shelf.
    azimuth_frame: str = "world"
    target_offset: float = 0.1            # m, look-at point within this of the fixture centre
    # What camera_info reports may differ from the true camera (calibration error): per frame
    # fx = fy reported off by up to +-this fraction, cx and cy by up to +-this many pixels.
    info_focal_error: float = 0.0
    info_principal_error_px: float = 0.0

    @property
    def nominal_focal_px(self) -> float:
        return (self.focal_px[0] + self.focal_px[1]) / 2.0

    def validate(self) -> CameraConfig:
        o = "camera"
        _check_int(o, "width", self.width, 16, 4096)
        _check_int(o, "height", self.height, 16, 4096)
        _check_interval(o, "focal_px", self.focal_px, 50.0, 5000.0)
        _check_range(o, "principal_offset_px", self.principal_offset_px, 0.0,
                     min(self.width, self.height) / 4)
        _check_interval(o, "distance", self.distance, 0.2, 10.0)
        _check_interval(o, "elevation_deg", self.elevation_deg, 5.0, 90.0)
        _check_interval(o, "azimuth_deg", self.azimuth_deg, -360.0, 720.0)
        _check_interval(o, "roll_deg", self.roll_deg, -180.0, 180.0)
        _check_range(o, "target_offset", self.target_offset, 0.0, 1.0)
        if self.azimuth_frame not in ("world", "fixture"):
            raise ConfigError(f"{o}.azimuth_frame = {self.azimuth_frame!r}: "
                              "expected one of ('world', 'fixture')")
        _check_range(o, "info_focal_error", self.info_focal_error, 0.0, 0.2)
        _check_range(o, "info_principal_error_px", self.info_principal_error_px, 0.0,
                     min(self.width, self.height) / 8)
        return self

    @property
    def info_differs(self) -> bool:
        """Whether camera_info is drawn apart from the true camera (else it is the camera)."""
        return self.info_focal_error > 0 or self.info_principal_error_px > 0


@dataclass(frozen=True)
class NoiseConfig:
    """Kinect-v1 structured-light noise (see training/noise.py for the models and citations).

    Each parameter is a fixed value or a (min, max) range drawn per frame (``draw``)."""

    enabled: bool = True
    model: str = "kinect_v1"              # the named sensor model (training/noise.py)
    baseline: float = 0.075               # m, IR projector to IR camera
    disparity_subpixel: int = 8           # disparity quantised to 1/8 px
    # Axial noise in disparity: sigma_z = z^2 sigma_d / (fx b), 1.3 mm at 1 m, 11.8 mm at 3 m
    # (fx 557.5; 1.6 / 14.2 mm with the 1/8 px quantisation; Nguyen et al. 2012: 1.9 / 14.0 mm).
    sigma_disparity_px: float = 0.055
    grazing_sigma: float = 1e-4           # m*sqrt(m), Nguyen's extra axial noise near 90 deg
    lateral_sigma_px: float = 0.5         # edge jitter (Handa et al. 2014)
    grazing_start_deg: float = 60.0       # dropout probability ramps from here ...
    grazing_full_deg: float = 85.0        # ... to 1 here (angle between ray and normal)
    speckle_rate: float = 4e-4            # seeds of speckle holes per pixel
    speckle_max_radius_px: int = 3
    min_range: float = 0.5                # m
    max_range: float = 4.5                # m
    # Calibration drift: a per-frame disparity offset, N(0, this) px, and a smooth random
    # disparity field (a few cycles across the image) of this standard deviation in px.
    bias_disparity_px: float = 0.0
    lowfreq_disparity_px: float = 0.0

    def validate(self) -> NoiseConfig:
        o = "noise"
        if not isinstance(self.enabled, bool):
            raise ConfigError(f"{o}.enabled = {self.enabled!r}: expected true or false")
        if self.model not in NOISE_MODELS:
            raise ConfigError(f"{o}.model = {self.model!r}: expected one of {NOISE_MODELS} "
                              "(a time-of-flight sensor is described in the tof section)")
        _validate_drawn(o, self, _NOISE_LIMITS, _NOISE_INTS)
        # Every draw must keep the ramp and the range ordered.
        if self.bounds("grazing_full_deg")[0] < self.bounds("grazing_start_deg")[1]:
            raise ConfigError(f"{o}.grazing_full_deg = {self.grazing_full_deg!r} must not be "
                              f"below grazing_start_deg = {self.grazing_start_deg!r}")
        if self.bounds("max_range")[0] <= self.bounds("min_range")[1]:
            raise ConfigError(f"{o}.max_range = {self.max_range!r} must exceed min_range = "
                              f"{self.min_range!r}")
        return self

    def bounds(self, name: str) -> tuple[float, float]:
        """A parameter's (lowest, highest) value: a range, or a fixed value twice."""
        value = getattr(self, name)
        return tuple(value) if isinstance(value, (tuple, list)) else (value, value)

    def midpoint(self, name: str) -> float:
        lo, hi = self.bounds(name)
        return (lo + hi) / 2

    def draw(self, rng: np.random.Generator) -> NoiseConfig:
        """This frame's sensor: every parameter given as a (min, max) range drawn uniformly
        (whole numbers for the integer ones), in field order; fixed ones stay, drawing
        nothing, so a spec without ranges makes exactly the frames it always made."""
        return _draw_parameters(self, _NOISE_LIMITS, _NOISE_INTS, rng)

    def drawn_per_frame(self) -> bool:
        return any(isinstance(getattr(self, n), (tuple, list)) for n in _NOISE_LIMITS)


# The sensor parameters a spec may fix or give as a (min, max) range drawn per frame, with
# their allowed limits.
_NOISE_LIMITS = {
    "baseline": (0.01, 0.5), "disparity_subpixel": (1, 64),
    "sigma_disparity_px": (0.0, 2.0), "grazing_sigma": (0.0, 0.01),
    "lateral_sigma_px": (0.0, 5.0), "grazing_start_deg": (0.0, 90.0),
    "grazing_full_deg": (0.0, 90.0), "speckle_rate": (0.0, 0.05),
    "speckle_max_radius_px": (0, 20), "min_range": (0.0, 10.0), "max_range": (0.0, 20.0),
    "bias_disparity_px": (0.0, 2.0), "lowfreq_disparity_px": (0.0, 2.0),
}
_NOISE_INTS = ("disparity_subpixel", "speckle_max_radius_px")
NOISE_PARAMETERS = tuple(_NOISE_LIMITS)  # what a manifest records of a frame's drawn sensor


@dataclass(frozen=True)
class TofConfig:
    """A time-of-flight sensor (training/tof.py), drawn instead of ``noise`` for a ``share`` of
    the frames: structurally different errors (no projector shadows, no disparity steps, but
    flying pixels, multipath and amplitude dropout), so no single noise signature is learnt.

    Each parameter is a fixed value or a (min, max) range drawn per frame, as for ``noise``."""

    share: float = 0.0                    # fraction of frames; 0 = never (draws nothing)
    sigma_1m: float = 0.002               # m, axial sd of a facing surface at 1 m (grows z^2)
    amplitude_cutoff: float = 0.02        # dropout below this return amplitude cos / z^2 ...
    amplitude_soft: float = 0.02          # ... ramping to none at cutoff + soft
    flying_pixel_rate: float = 0.5        # share of depth-edge pixels mixed fore/background
    edge_jump_m: float = 0.05             # a depth edge: neighbours this much apart
    multipath_gain: float = 0.3           # depth excess in concave corners, x the hollow depth
    multipath_window_px: int = 15         # size of the neighbourhood that defines a hollow
    depth_bias_m: float = 0.0             # per-frame offset, N(0, this)
    dropout_rate: float = 0.0005          # isolated invalid pixels per pixel
    min_range: float = 0.2                # m
    max_range: float = 5.0                # m

    def validate(self) -> TofConfig:
        _validate_shared_sensor("tof", self, _TOF_LIMITS, _TOF_INTS)
        return self

    bounds = NoiseConfig.bounds
    midpoint = NoiseConfig.midpoint

    def draw(self, rng: np.random.Generator) -> TofConfig:
        """This frame's ToF sensor, drawn like ``NoiseConfig.draw``."""
        return _draw_parameters(self, _TOF_LIMITS, _TOF_INTS, rng)


_TOF_LIMITS = {
    "sigma_1m": (0.0, 0.1), "amplitude_cutoff": (0.0, 1.0), "amplitude_soft": (0.0, 1.0),
    "flying_pixel_rate": (0.0, 1.0), "edge_jump_m": (0.005, 1.0),
    "multipath_gain": (0.0, 2.0), "multipath_window_px": (3, 99),
    "depth_bias_m": (0.0, 0.1), "dropout_rate": (0.0, 0.05),
    "min_range": (0.0, 10.0), "max_range": (0.0, 20.0),
}
_TOF_INTS = ("multipath_window_px",)
TOF_PARAMETERS = tuple(_TOF_LIMITS)


@dataclass(frozen=True)
class StereoConfig:
    """An active-stereo sensor (training/stereo.py; RealSense-D400-like): two infrared cameras
    ``baseline`` m apart matched by blocks of ``window_px``, drawn instead of ``noise`` for a
    ``share`` of the frames. The third sensor model: its errors are shaped by block matching
    (foreground fattened over the background, noise correlated across a block, mismatched
    islands of wrong depth), which neither the structured-light nor the ToF model makes.

    Each parameter is a fixed value or a (min, max) range drawn per frame, as for ``noise``."""

    share: float = 0.0                    # fraction of frames; 0 = never (draws nothing)
    baseline: float = 0.05                # m, between the two infrared cameras
    disparity_subpixel: int = 32          # disparity quantised to 1/32 px
    sigma_disparity_px: float = 0.08      # subpixel matching error, per block
    window_px: int = 7                    # matching block (even: the next odd size)
    fattening_px: int = 2                 # foreground bled over the background at an edge
    grazing_start_deg: float = 65.0       # dropout probability ramps from here ...
    grazing_full_deg: float = 85.0        # ... to 1 here
    mismatch_rate: float = 1e-4           # seeds of wrongly matched islands per pixel
    mismatch_max_radius_px: int = 3
    mismatch_disparity_px: float = 4.0    # their disparity off by up to this, either way
    speckle_rate: float = 2e-4            # seeds of holes per pixel (no match found)
    speckle_max_radius_px: int = 3
    bias_disparity_px: float = 0.0        # calibration drift, as noise.bias_disparity_px
    lowfreq_disparity_px: float = 0.0     # ... and noise.lowfreq_disparity_px
    min_range: float = 0.3                # m
    max_range: float = 6.0                # m

    def validate(self) -> StereoConfig:
        _validate_shared_sensor("stereo", self, _STEREO_LIMITS, _STEREO_INTS)
        if self.bounds("grazing_full_deg")[0] < self.bounds("grazing_start_deg")[1]:
            raise ConfigError(f"stereo.grazing_full_deg = {self.grazing_full_deg!r} must not "
                              f"be below grazing_start_deg = {self.grazing_start_deg!r}")
        return self

    bounds = NoiseConfig.bounds
    midpoint = NoiseConfig.midpoint

    def draw(self, rng: np.random.Generator) -> StereoConfig:
        """This frame's stereo sensor, drawn like ``NoiseConfig.draw``."""
        return _draw_parameters(self, _STEREO_LIMITS, _STEREO_INTS, rng)


_STEREO_LIMITS = {
    "baseline": (0.01, 0.5), "disparity_subpixel": (1, 64),
    "sigma_disparity_px": (0.0, 2.0), "window_px": (1, 31), "fattening_px": (0, 15),
    "grazing_start_deg": (0.0, 90.0), "grazing_full_deg": (0.0, 90.0),
    "mismatch_rate": (0.0, 0.01), "mismatch_max_radius_px": (0, 20),
    "mismatch_disparity_px": (0.0, 64.0), "speckle_rate": (0.0, 0.05),
    "speckle_max_radius_px": (0, 20), "bias_disparity_px": (0.0, 2.0),
    "lowfreq_disparity_px": (0.0, 2.0), "min_range": (0.0, 10.0), "max_range": (0.0, 20.0),
}
_STEREO_INTS = ("disparity_subpixel", "window_px", "fattening_px", "mismatch_max_radius_px",
                "speckle_max_radius_px")
STEREO_PARAMETERS = tuple(_STEREO_LIMITS)


def _validate_shared_sensor(owner: str, cfg: Any, limits: dict, ints: tuple[str, ...]
                            ) -> None:
    """A sensor drawn for a ``share`` of the frames (``tof``, ``stereo``): the share, every
    parameter within its limits, and a range that leaves room to measure when it is drawn."""
    _check_range(owner, "share", cfg.share, 0.0, 1.0)
    _validate_drawn(owner, cfg, limits, ints)
    if cfg.share > 0 and cfg.bounds("max_range")[0] <= cfg.bounds("min_range")[1]:
        raise ConfigError(f"{owner}.max_range = {cfg.max_range!r} must exceed min_range = "
                          f"{cfg.min_range!r}")


def _validate_drawn(owner: str, cfg: Any, limits: dict, ints: tuple[str, ...]) -> None:
    """Every sensor parameter a fixed value or a (min, max) range within its limits."""
    for name, (lo, hi) in limits.items():
        value = getattr(cfg, name)
        check = _check_int if name in ints else _check_range
        if isinstance(value, (tuple, list)):
            _check_interval(owner, name, value, lo, hi)
            if name in ints:
                for k, v in enumerate(value):
                    _check_int(owner, f"{name}[{k}]", v, lo, hi)
        else:
            check(owner, name, value, lo, hi)


def _draw_parameters(cfg: Any, limits: dict, ints: tuple[str, ...], rng: np.random.Generator):
    """``cfg`` with every parameter given as a range drawn uniformly (whole numbers for the
    integer ones), in field order; fixed ones stay and draw nothing."""
    drawn = {}
    for name in limits:
        value = getattr(cfg, name)
        if isinstance(value, (tuple, list)):
            lo, hi = value
            drawn[name] = (int(rng.integers(lo, hi + 1)) if name in ints
                           else float(rng.uniform(lo, hi)))
    return dataclasses.replace(cfg, **drawn) if drawn else cfg


@dataclass(frozen=True)
class DiscoverConfig:
    """DBSCAN on the final object states (see training/discover.py for the features)."""

    # Chosen in the middle of a plateau: eps 0.10-0.12 with min_samples 0.3-0.5 % of the
    # objects all give exactly 3 clusters (ARI >= 0.995) at 10,000 episodes and for 5 seeds at
    # 2,000; 1 % splits the sparse stuck_on_rim cluster on some seeds.
    eps: float = 0.12
    # min_samples scales with the data so density means the same at 2,000 and 10,000 episodes.
    min_samples_fraction: float = 0.005
    min_samples_floor: int = 10
    # Discovery names each cluster in the target region's terms (DESCRIPTORS); this
    # maps those descriptors to the task's words, and names the fixture's class. The defaults
    # are the default task's words (docs/interface.md §2, §3), like every default here.
    outcome_names: tuple[tuple[str, str], ...] = (
        ("inside", "success"), ("outside", "fell_outside"), ("partly_inside", "stuck_on_rim"))
    fixture_name: str = "container"
    # The geometric yardstick's "inside" (discover.py): besides the centre of mass over the
    # footprint, "top": the object's top below the region's top (an open box: walls hold the
    # sides); "footprint": all of the object over the footprint (a board: nothing holds them).
    yardstick_inside: str = "top"

    def min_samples(self, n_objects: int) -> int:
        return max(self.min_samples_floor, round(self.min_samples_fraction * n_objects))

    def validate(self) -> DiscoverConfig:
        _check_range("discover", "eps", self.eps, 1e-4, 10.0)
        _check_range("discover", "min_samples_fraction", self.min_samples_fraction, 0.0, 0.5)
        _check_int("discover", "min_samples_floor", self.min_samples_floor, 1, 10000)
        self._validate_names()
        if self.yardstick_inside not in ("top", "footprint"):
            raise ConfigError(f"discover.yardstick_inside = {self.yardstick_inside!r}: "
                              "expected one of ('top', 'footprint')")
        return self

    def _validate_names(self) -> None:
        names = dict(self.outcome_names)
        unknown = sorted(set(names) - set(DESCRIPTORS))
        if unknown or len(names) != len(self.outcome_names):
            raise ConfigError(f"discover.outcome_names: keys {unknown or list(names)} must be "
                              f"distinct descriptors from {DESCRIPTORS}")
        # Every descriptor discovery may find gets a word (its own, when the spec has none).
        words = [self.outcome_name(d) for d in DESCRIPTORS] + [self.fixture_name]
        bad = [w for w in words if not isinstance(w, str)
               or not re.fullmatch(r"[a-z][a-z0-9_]*", w) or w in RESERVED_WORDS]
        if bad or len(set(words)) != len(words):
            raise ConfigError(f"discover.outcome_names / fixture_name: {words} must be distinct "
                              f"lower-case words (a-z, 0-9, _), none of {RESERVED_WORDS}")

    def outcome_name(self, descriptor: str) -> str:
        """The task's word for a descriptor (the descriptor itself when the spec has none)."""
        return dict(self.outcome_names).get(descriptor, descriptor)


@dataclass(frozen=True)
class DatasetConfig:
    """The whole dataset run: how many episodes, the seed, the split, the parallelism."""

    task: str = "default"                 # the scene spec this came from (training/scene.py)
    episodes: int = 10_000
    seed: int = 0
    val_fraction: float = 0.05
    workers: int = 2
    chunk_size: int = 50                  # episodes per resumable unit of work
    scene: SceneConfig = field(default_factory=SceneConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    tof: TofConfig = field(default_factory=TofConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    discover: DiscoverConfig = field(default_factory=DiscoverConfig)

    def validate(self) -> DatasetConfig:
        if not isinstance(self.task, str) or not self.task:
            raise ConfigError(f"dataset.task = {self.task!r}: expected a spec name")
        _check_int("dataset", "episodes", self.episodes, 1, 10_000_000)
        _check_int("dataset", "seed", self.seed, 0, 2**63 - 1)
        _check_range("dataset", "val_fraction", self.val_fraction, 0.0, 0.5)
        _check_int("dataset", "workers", self.workers, 1, 256)
        _check_int("dataset", "chunk_size", self.chunk_size, 1, 100_000)
        self.scene.validate()
        self.camera.validate()
        self.noise.validate()
        self.tof.validate()
        self.stereo.validate()
        if self.tof.share + self.stereo.share > 1.0 + 1e-9:
            raise ConfigError(f"tof.share = {self.tof.share} and stereo.share = "
                              f"{self.stereo.share}: together at most 1 (the rest of the "
                              "frames come from the noise section's sensor)")
        self.discover.validate()
        self._validate_camera_sees_fixture()
        return self

    def _validate_camera_sees_fixture(self) -> None:
        """The sensor must measure the fixture from every distance of the envelope, and the
        look-at point must stay over the fixture's inner footprint."""
        near, far = self.camera.distance
        sensors = [("sensor", "noise", self.noise)]
        if self.tof.share > 0:
            sensors.append(("ToF sensor", "tof", self.tof))
        if self.stereo.share > 0:
            sensors.append(("stereo sensor", "stereo", self.stereo))
        for label, section, sensor in sensors if self.noise.enabled else ():
            sensor_near = sensor.bounds("min_range")[1]  # the narrowest range any frame draws
            sensor_far = sensor.bounds("max_range")[0]
            if near < sensor_near or far > sensor_far:
                raise ConfigError(
                    f"camera.distance = {list(self.camera.distance)} m: the {label} measures "
                    f"{sensor_near}-{sensor_far} m ({section}.min_range, {section}.max_range), "
                    "so it could not see the fixture from every distance")
        smallest_half = self.scene.smallest_half_width
        if self.camera.target_offset > smallest_half:
            raise ConfigError(
                f"camera.target_offset = {self.camera.target_offset} m: the look-at point "
                f"could leave the fixture, whose smallest inner half-width is "
                f"{smallest_half:.3f} m")


def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def _legacy_scene(data: dict) -> dict:
    """Scene fields of configs saved before the scene spec (a square open box, fixed wall
    height and release height, an absolute release offset, fields named after the default
    task's container) in today's terms."""
    data = dict(data)
    for old, new in (("container_offset", "fixture_offset"),
                     ("container_yaw_deg", "fixture_yaw_deg"),
                     ("release_above_rim", "release_height")):
        if old in data:
            data.setdefault(new, data.pop(old))
    if "container_inner_size" in data:
        side = data.pop("container_inner_size")
        data.setdefault("inner_size_x", (side, side))
        data.setdefault("inner_size_y", (side, side))
    for name in ("wall_height", "release_height"):
        if isinstance(data.get(name), (int, float)):
            data[name] = (data[name], data[name])
    size = data.get("table_size")
    if isinstance(size, (list, tuple)) and all(isinstance(v, (int, float)) for v in size):
        data["table_size"] = tuple((v, v) for v in size)   # a fixed (x, y) pair
    if "release_offset" in data:
        offset = data.pop("release_offset")
        data.setdefault("release_margin", offset - data.get("inner_size_x", (1.0,))[0] / 2)
    return data


def _tuples(value: Any) -> Any:
    """JSON and YAML lists (also nested) -> tuples, as the frozen configs hold them."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return tuple((k, _tuples(v)) for k, v in value.items())
    return value


def _from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (nested) frozen dataclass from a dict; unknown keys are an error."""
    if not isinstance(data, dict):
        raise ConfigError(f"{cls.__name__}: expected a mapping of fields, got {data!r}")
    if cls is SceneConfig:
        data = _legacy_scene(data)
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown field(s) {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        default = getattr(cls(), name) if _has_default(cls, name) else None
        if dataclasses.is_dataclass(default):
            kwargs[name] = _from_dict(type(default), value)
        else:
            kwargs[name] = _tuples(value)
    return cls(**kwargs)


def _has_default(cls: type, name: str) -> bool:
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def dataset_config_from_dict(data: dict) -> DatasetConfig:
    return _from_dict(DatasetConfig, data).validate()


def save_json(path: Path, data: Any) -> None:
    """Write JSON atomically (temp file + rename): an interrupted run never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    tmp.replace(path)


def load_json(path: Path) -> Any:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist: run the stage that writes it first")
    return json.loads(path.read_text())


# Network options added after the first models, with the value that means "not used" (what
# every run before them had): left out of model_args when unused, and not a difference when a
# run saved before them resumes (train.ADDED_TRAIN_FIELDS).
LATER_NETWORK_OPTIONS = {"space_to_depth": 1, "full_size_head": 0, "head_width": 0}


def _check_relief_option(owner: str, name: str, value: Any, check, relief_window_px: int | None,
                         off: int | float = 0) -> None:
    """A relief option: ``off`` or what ``check`` (model.check_relief_*) accepts; the options
    that shape the relief channel (``relief_window_px`` given) need that channel on. A window
    is off at the integer 0 only (not 0.0, not False), a float option at 0 or 0.0."""
    off_types = (int, float) if isinstance(off, float) else (int,)
    if value == off and type(value) in off_types:
        return
    try:
        check(value)
    except ValueError as exc:
        raise ConfigError(f"{owner}.{exc} (or 0: off)") from None
    if relief_window_px is not None and not relief_window_px:
        raise ConfigError(f"{owner}.{name} = {value} needs relief_window_px: it shapes the "
                          "relief channel")


@dataclass(frozen=True)
class TrainConfig:
    """Training of the outcome FCN (training/train.py). Defaults train the shipped model."""

    input_size: tuple[int, int] = (160, 120)          # (W, H) working resolution
    base_width: int = 8
    levels: int = 5                       # a 5th stage: whole-scene context for ~1 ms more
    # Width cap: uncapped, the 5th stage's 256 channels held 3/4 of the weights (7 MB file).
    max_width: int = 128
    decoder_convs: int = 1
    # 2: the input folded 2 x 2 into channels, convs on the half-size grid, logits upsampled
    # back (model.OutcomeFCN); a working size twice as fine for about the same network cost.
    space_to_depth: int = 1
    # Channels of a thin head at the working size for a folded network (model.OutcomeFCN):
    # boundaries from full-size evidence instead of upsampled logits; 0 = none.
    full_size_head: int = 0
    # Channels of the last decoder block, which the 1x1 head reads (model.OutcomeFCN); 0 =
    # base_width. For a thin first level (base_width under the class count).
    head_width: int = 0
    # Tote model 0.6.0: 13 epochs of 19,000 images, 47 min on 2 cores in bf16 (0.37 s a step
    # in the loop). In fp32 a step takes about 1.05 s, and the schedule is fitted to
    # max_minutes after the first epoch (train.fitted_epochs): about 5 epochs of 19,000
    # (model 0.3.0 trained 7 of 13,300 in 51 min).
    epochs: int = 13
    batch_size: int = 32
    lr: float = 1.5e-3
    weight_decay: float = 1e-4
    # Validation and checkpoints use an exponential moving average of the weights: the raw
    # weights swung between 0.31 and 0.88 all-correct from one epoch to the next at peak LR.
    ema_decay: float = 0.998              # per step; 0 turns the average off
    max_minutes: float = 58.0             # the schedule fits it; stop (keep the best) past it
    class_weight_power: float = 0.3       # weights = (1 / class frequency) ** power
    # Sampling weight of training images tagged near_boundary (hard_cases.py: an object within
    # 2 cm of the task's inside / partly-inside boundary, where most mistakes are); 1 = uniform
    # epochs (a permutation), > 1 draws them more often (with replacement). 2.5 on the quick
    # profile of the default task: near-rim mistakes 11 -> 8 (validation) and 34 -> 27 (seed-1
    # set), the others unchanged.
    near_boundary_weight: float = 2.5
    # Sampling weight of training images with an outcome present under
    # size_recall.SMALL_OUTCOME_PIXELS (at 640 x 480; train.small_outcome_sample_weights),
    # multiplying the near-boundary weight: the tote model missed half its fallen objects
    # under 800 px, on its own training images as on validation (it underfits them). 1 = off.
    small_outcome_weight: float = 1.0
    # Sampling weight of training images where two different outcomes touch in the working-size
    # labels (train.touching_outcomes_sample_weights), multiplying the weights above: on the
    # default task 0.13.0 got 13 of the 102 such images among its first 1,000 training images
    # wrong against 17 of the other 898 (a success box under a box stacked on it above the rim
    # painted with the stacked box's outcome). Read from the labels, so any task has it. 1 = off.
    touching_outcomes_weight: float = 1.0
    # Sampling weight of training images where two objects touch in the frame, whatever their
    # outcomes (overlaps.frames_with_touching_objects: the objects cast again with ids of their
    # own at the working size), multiplying the weights above: the balanced form of the weight
    # above, which broke stacks of success boxes as often as it fixed stacked boxes. Neither
    # got the default's stacked boxes right (docs/experiments.md). 1 = off.
    touching_objects_weight: float = 1.0
    # Weight of an auxiliary training target (losses.ObjectDistanceHead): on every object pixel,
    # its distance to the nearest pixel that is not the same object (overlaps.object_distance,
    # from the objects cast again with ids of their own), read out of the features the class
    # head reads. Labels cannot tell two touching objects of one outcome apart, nor where a
    # stacked box ends and the box under it begins; this target asks the features for it. The
    # head is for training only: the checkpoint's network, and inference, stay as they are.
    # Whole images without roll only (not carried through crops or the roll). On the default
    # task, weight 1: 0.977 against 0.982 (docs/experiments.md). 0 = off.
    object_distance_weight: float = 0.0
    augment: bool = True
    # Re-drawn axial noise per training image: U(0, aug_noise) x the sensor's own noise at the
    # working size (redrawn_noise.SENSOR_NOISE_PER_Z2). Before model 0.1.5 it was ~7x the sensor's.
    aug_noise: float = 1.0
    # Share of training images that lose their depth over large smooth regions, up to 35 % of
    # the image (holes.no_return_holes: real frames lose whole surfaces, our sensor models
    # mostly speckles); labels there are ignored. 0 = off.
    aug_holes: float = 0.0
    # Camera roll added per training image, U(-aug_roll_deg, aug_roll_deg) on top of the
    # spec's own (roll.roll_images: the image turned about its principal point, exact for
    # depth along the optical axis). 0 = off.
    aug_roll_deg: float = 0.0
    # Outlier islands per training image (islands.working_islands): a rate U(0, aug_islands)
    # per 640 x 480 pixel of small patches of wrong depth, as disparity sensors' wrong
    # matches, labels kept; on whole images and on train_crop's crops alike. 0 = off.
    aug_islands: float = 0.0
    # Draw each of those islands as a disc of its own area in working pixels (several pixels
    # at 320 x 240) instead of in one working pixel (islands.disc_kernels). Off = the islands
    # of default model 0.17.0.
    aug_islands_discs: bool = False
    # Share of training images cut at a range limit drawn in their far depths, with the
    # truncation their noise (the sensor's and the re-drawn) gives: the band of nearer-reading
    # pixels a sensor leaves along its maximum range (training/range_limit.py); on whole images
    # and on train_crop's crops alike. 0 = off.
    aug_range_limit: float = 0.0
    # (w, h): train on one crop of this size per image, cut from the input_size cache, its
    # heights above the support plane fitted on the whole image (training/crops.py): a finer
    # input_size at the coarse size's cost per step; inference runs on the whole image.
    # None = whole images.
    # Not with nearest_height or relief_window_px.
    train_crop: tuple[int, int] | None = None
    # Weight of the per-image outcome IoU (Lovász-softmax) loss added to cross-entropy
    # (losses.py); 0 = cross-entropy alone. 0.5 (model 0.1.6): fewer split objects; image
    # all-correct 0.982 -> 0.986 (validation), 0.980 -> 0.982 (seed-1), 0.980 -> 0.987 on the
    # first 1,000 training images, for ~6 % more time per step (bench/train_step.py).
    lovasz_weight: float = 0.5
    # Object-balanced cross-entropy (losses.object_balance_weights): an outcome's connected
    # component smaller than this many working-size pixels weighs as much as one of this
    # size, so small objects (slivers at the frame's edge, far objects on a room floor) count
    # like large ones, as they do in the image metric; 0 = off (plain class weights).
    object_balance_pixels: int = 0
    # A fourth input channel, the heights' local relief (relief.local_relief) over a square of
    # this many working pixels: a small object reads its own height above whatever surface it
    # lies on (a room floor 0.75 m below the table included); 0 = off (three channels).
    relief_window_px: int = 0
    # The relief of the heights' mean over a square of this many working pixels
    # (relief.valid_mean), so that sensor noise does not read as relief on a flat surface;
    # needs relief_window_px; 0 = off (the relief of the heights themselves).
    relief_smoothing_px: int = 0
    # The relief's surface (its opening) found on the heights' mean over a square of this
    # many working pixels (relief.local_relief), so that the erosion's low tail, which grows
    # with the noise, stays narrow; needs relief_window_px; 0 = off (the surface from the
    # same heights as each pixel's own).
    relief_base_px: int = 0
    # The relief lowered by this many deviations of the smoothed heights' noise, measured
    # around each pixel by a median (relief.local_noise_sd), so that a noisy far floor reads
    # about as flat as a quiet one; needs relief_smoothing_px; 0 = off.
    relief_noise_sds: float = 0.0
    # The relief of what lies below the table top measured from the room floor beneath it
    # (floor.heights_beneath_support): beside the table top an object on the room floor is
    # part of a surface the opening fits in and reads no relief. Needs relief_window_px and
    # a task on a table. False = off.
    relief_beneath_support: bool = False
    # One more input channel, the height of each working pixel's near side
    # (model.nearest_depth): the area resize averages a 1 cm rim, and the top edge of an object
    # leaning on it, with what lies beside them; the nearest of the block's four cells keeps
    # their tops' true height. False = off.
    nearest_height: bool = False
    # Height channel from each image's own camera (the dataset's camera records; camera_info
    # on the robot) instead of the envelope's nominal one, whose focal length can be 6 % off:
    # 3 mm of height error at the rim on average, up to 14 mm, as much as a near-rim box's
    # whole margin. Off: the nominal camera, plus a +-4 % whole-scene distance change in
    # augmentation. On the quick profile (model 0.1.7's recipe): 0.978 / 0.972 (validation /
    # seed-1) with camera_info, 0.976 / 0.967 without, against 0.976 / 0.967 for a nominal-camera
    # model.
    camera_intrinsics: bool = True
    device: str = "auto"                  # cpu | cuda | auto
    # auto: fp16 on CUDA, bf16 on a CPU with native bf16 (AVX512-BF16/AMX), else fp32
    # (train.resolve_precision). bf16 | off force it.
    amp: str = "auto"
    # NHWC activations: ~0.7x the fp32 step time on the 2-core EPYC, ~0.5x with bf16, but
    # 1.48x the contiguous bf16 step on an AMX Xeon (bench/train_step.py). "auto": the
    # faster on this machine, timed before the first epoch (train.layout_step_seconds);
    # true / false (--channels-last / --no-channels-last) force it.
    channels_last: bool | str = "auto"
    threads: int = 2
    seed: int = 0

    def validate(self) -> TrainConfig:
        o = "train"
        w, h = self.input_size
        _check_range(o, "input_size[0]", w, 16, 4096)
        _check_range(o, "input_size[1]", h, 16, 4096)
        _check_int(o, "base_width", self.base_width, 2, 256)
        _check_int(o, "levels", self.levels, 1, 6)
        _check_int(o, "decoder_convs", self.decoder_convs, 1, 2)
        _check_int(o, "max_width", self.max_width, self.base_width, 4096)
        _check_int(o, "space_to_depth", self.space_to_depth, 1, 2)
        # 32 = model.FULL_SIZE_HEAD_MAX, repeated: validating a config does not import torch.
        _check_int(o, "full_size_head", self.full_size_head, 0, 32)
        if self.full_size_head and self.space_to_depth == 1:
            raise ConfigError(f"{o}.full_size_head = {self.full_size_head} needs "
                              "space_to_depth 2: an unfolded network already works at full size")
        # 64 = model.HEAD_WIDTH_MAX, repeated for the same reason.
        _check_int(o, "head_width", self.head_width, 0, 64)
        if self.head_width and (self.head_width <= self.base_width or self.full_size_head):
            raise ConfigError(f"{o}.head_width = {self.head_width} must exceed base_width "
                              f"({self.base_width}) and cannot join a full_size_head")
        _check_int(o, "epochs", self.epochs, 1, 10_000)
        _check_int(o, "batch_size", self.batch_size, 1, 4096)
        _check_range(o, "lr", self.lr, 1e-6, 1.0)
        _check_range(o, "weight_decay", self.weight_decay, 0.0, 1.0)
        _check_range(o, "ema_decay", self.ema_decay, 0.0, 0.99999)
        _check_range(o, "max_minutes", self.max_minutes, 0.01, 10_000)
        _check_range(o, "class_weight_power", self.class_weight_power, 0.0, 2.0)
        _check_range(o, "near_boundary_weight", self.near_boundary_weight, 1.0, 100.0)
        _check_range(o, "small_outcome_weight", self.small_outcome_weight, 1.0, 100.0)
        _check_range(o, "touching_outcomes_weight", self.touching_outcomes_weight, 1.0, 100.0)
        _check_range(o, "touching_objects_weight", self.touching_objects_weight, 1.0, 100.0)
        _check_range(o, "object_distance_weight", self.object_distance_weight, 0.0, 100.0)
        if self.object_distance_weight and (self.train_crop is not None or self.aug_roll_deg):
            raise ConfigError(f"{o}.object_distance_weight = {self.object_distance_weight} "
                              "needs whole images without roll: its target is not carried "
                              "through train_crop or aug_roll_deg yet")
        _check_range(o, "aug_noise", self.aug_noise, 0.0, 20.0)
        _check_range(o, "aug_holes", self.aug_holes, 0.0, 1.0)
        if self.aug_holes and not self.augment:
            raise ConfigError(f"{o}.aug_holes = {self.aug_holes} needs augment (the holes are "
                              "drawn by the augmentation): set augment or aug_holes 0")
        _check_range(o, "aug_islands", self.aug_islands, 0.0, 0.01)
        if self.aug_islands and not self.augment:
            raise ConfigError(f"{o}.aug_islands = {self.aug_islands} needs augment (the "
                              "islands are drawn by the augmentation): set augment or "
                              "aug_islands 0")
        if self.aug_islands_discs and not self.aug_islands:
            raise ConfigError(f"{o}.aug_islands_discs shapes the islands aug_islands draws: "
                              "set aug_islands above 0 or aug_islands_discs off")
        _check_range(o, "aug_range_limit", self.aug_range_limit, 0.0, 1.0)
        if self.aug_range_limit and not self.augment:
            raise ConfigError(f"{o}.aug_range_limit = {self.aug_range_limit} needs augment (the "
                              "limit is drawn by the augmentation): set augment or "
                              "aug_range_limit 0")
        if self.aug_range_limit and self.nearest_height:
            raise ConfigError(f"{o}.aug_range_limit is not carried to the near-side depths of "
                              "nearest_height yet: turn one of them off")
        _check_range(o, "aug_roll_deg", self.aug_roll_deg, 0.0, 45.0)
        if self.aug_roll_deg and not self.augment:
            raise ConfigError(f"{o}.aug_roll_deg = {self.aug_roll_deg} needs augment (the roll "
                              "is drawn by the augmentation): set augment or aug_roll_deg 0")
        if self.train_crop is not None:
            self._check_train_crop(o)
        # Only a level other than off and the default can be told from "left alone"; the
        # class attribute is the field's default.
        default_noise = TrainConfig.aug_noise
        if not self.augment and self.aug_noise not in (0.0, default_noise):
            raise ConfigError(f"{o}.aug_noise = {self.aug_noise} needs augment (the noise is "
                              f"re-drawn by the augmentation): set augment or aug_noise 0 "
                              f"or {default_noise:g}")
        _check_range(o, "lovasz_weight", self.lovasz_weight, 0.0, 100.0)
        _check_int(o, "object_balance_pixels", self.object_balance_pixels, 0, 1_000_000)
        from task_outcome_ros.model import (
            check_relief_base,
            check_relief_noise_sds,
            check_relief_smoothing,
            check_relief_window,
        )

        _check_relief_option(o, "relief_window_px", self.relief_window_px,
                             check_relief_window, None)
        _check_relief_option(o, "relief_smoothing_px", self.relief_smoothing_px,
                             check_relief_smoothing, self.relief_window_px)
        _check_relief_option(o, "relief_base_px", self.relief_base_px,
                             check_relief_base, self.relief_window_px)
        _check_relief_option(o, "relief_noise_sds", self.relief_noise_sds,
                             check_relief_noise_sds, self.relief_window_px, off=0.0)
        if self.relief_noise_sds and not self.relief_smoothing_px:
            raise ConfigError(f"{o}.relief_noise_sds = {self.relief_noise_sds} needs "
                              "relief_smoothing_px: the noise is that of the heights' mean")
        _check_int(o, "threads", self.threads, 1, 256)
        for name, value, allowed in (("device", self.device, ("cpu", "cuda", "auto")),
                                     ("amp", self.amp, ("auto", "bf16", "off"))):
            if value not in allowed:
                raise ConfigError(f"{o}.{name} = {value!r}: expected one of {allowed}")
        if not (isinstance(self.channels_last, bool) or self.channels_last == "auto"):
            raise ConfigError(f"{o}.channels_last = {self.channels_last!r}: expected true, "
                              "false or \"auto\"")
        if self.relief_beneath_support is True and not self.relief_window_px:
            raise ConfigError(f"{o}.relief_beneath_support needs relief_window_px: it shapes "
                              "the relief channel")
        for name in ("camera_intrinsics", "nearest_height", "relief_beneath_support"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{o}.{name} = {getattr(self, name)!r}: expected true/false")
        return self

    def _check_train_crop(self, o: str) -> None:
        cw, ch = self.train_crop
        _check_int(o, "train_crop[0]", cw, 32, self.input_size[0])
        _check_int(o, "train_crop[1]", ch, 32, self.input_size[1])
        if not self.augment:
            raise ConfigError(f"{o}.train_crop needs augment (the crops are drawn by it)")
        unsupported = [name for name in ("nearest_height", "relief_window_px")
                       if getattr(self, name)]
        if unsupported:
            raise ConfigError(f"{o}.train_crop does not combine with {', '.join(unsupported)}: "
                              "a crop's heights come from planes fitted on the whole image, "
                              "those channels are not made from them (training/crops.py)")

    @property
    def model_args(self) -> dict:
        from task_outcome_ros.labels import DEFAULT_TABLE
        from task_outcome_ros.model import IN_CHANNELS

        # The default task's class count; train.py sets the dataset's own table's.
        args = {"in_channels": IN_CHANNELS, "num_classes": DEFAULT_TABLE.num_classes,
                "base_width": self.base_width, "levels": self.levels,
                "decoder_convs": self.decoder_convs, "max_width": self.max_width}
        # Options added later are recorded only when used, so that an unfolded network's
        # checkpoint still builds on a runtime older than them (package 0.7.0).
        for name, unused in LATER_NETWORK_OPTIONS.items():
            if getattr(self, name) != unused:
                args[name] = getattr(self, name)
        return args
