"""Open boxes shaped like real totes and trays (training/fixture.py ``Fixture``): walls leaning
out, a lip round the rim, handle holes in the x walls. What the physics builds, what the
renderer draws and what discovery measures must agree on that geometry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from task_outcome_ros.labels import DEFAULT_TABLE, FIXTURE
from training.config import ConfigError, SceneConfig
from training.fixture import (
    FIN_MAX,
    HANDLE_DROP,
    HANDLE_HEIGHT,
    Fixture,
    draw_fixture,
    euler_rotation,
    fixture_from_record,
)
from training.geometry import geometric_outcome, object_measurements
from training.render import Camera, look_at, render, scene_boxes
from training.scene import load_scene

pytestmark = pytest.mark.unit

FLARE = 15.0
# A 0.6 x 0.4 m tray-like tote, walls 0.2 m high leaning 15 deg out, a 2 cm lip, handle holes.
TRAY = Fixture(half_x=0.3, half_y=0.2, wall_height=0.2, wall_thickness=0.01,
               bottom_thickness=0.01, flare_deg=FLARE, lip_width=0.02, handle_holes=True,
               x=0.0, y=0.0, yaw=0.0, base_z=0.0)
RUN = math.tan(math.radians(FLARE))   # the walls' outward run per metre of rise


def _inside_a_solid(fixture: Fixture, point) -> bool:
    """Whether a fixture-frame point lies in any of the fixture's solids."""
    for half, centre, turn in fixture.solid_boxes():
        local = euler_rotation(turn).T @ (np.asarray(point, float) - np.asarray(centre))
        if np.all(np.abs(local) <= np.asarray(half) + 1e-9):
            return True
    return False


def test_leaning_walls_rise_from_the_footprint_to_the_wider_opening():
    t = TRAY.wall_thickness
    for z in (0.02, 0.1, 0.17):
        inner_face = TRAY.half_x + z * RUN
        # Just inside the inner face is open; just outside it is wall, along both axes (on
        # the end wall beside its handle hole).
        assert not _inside_a_solid(TRAY, (inner_face - 0.002, 0.15, z))
        assert _inside_a_solid(TRAY, (inner_face + 0.002, 0.15, z))
        assert _inside_a_solid(TRAY, (0.0, -(TRAY.half_y + z * RUN + 0.002), z))
        assert not _inside_a_solid(TRAY, (inner_face + 0.002 + t / math.cos(math.radians(FLARE))
                                          + 0.002, 0.15, z))
    region = TRAY.region()
    assert region.half_at(0.0) == pytest.approx([0.3, 0.2])
    assert region.half_at(0.2) == pytest.approx([0.3 + 0.2 * RUN, 0.2 + 0.2 * RUN])
    # The rim and lip close the top: the outer footprint is the opening plus wall and lip.
    assert TRAY.outer_half_footprint() == pytest.approx(
        region.half_at(0.2) + t / math.cos(math.radians(FLARE)) + 0.02)


def test_leaning_walls_meet_at_the_corners_without_fins_or_gaps():
    """A leaning wall narrows towards its foot: built from strips, its corners neither leave
    a slit nor reach more than FIN_MAX past the next wall's outside."""
    t = TRAY.wall_thickness
    rim = t / math.cos(math.radians(FLARE))
    for z in np.linspace(0.01, 0.185, 12):
        half_x, half_y = TRAY.region().half_at(z)
        # Across the corner seam, from the opening inward to the outside of both walls: solid.
        for d in np.linspace(0.001, rim - 0.001, 4):
            assert _inside_a_solid(TRAY, (half_x + d, half_y + d, z)), (z, d)
        # Diagonally out past both outer faces by more than FIN_MAX: nothing.
        beyond = rim + FIN_MAX + 0.002
        assert not _inside_a_solid(TRAY, (half_x + beyond, half_y + beyond, z)), z
        assert not _inside_a_solid(TRAY, (half_x + rim / 2, half_y + beyond, z)), z
        assert not _inside_a_solid(TRAY, (half_x + beyond, half_y + rim / 2, z)), z


def test_a_handle_hole_opens_each_end_wall_below_the_rim():
    along_slope = TRAY.wall_height / math.cos(math.radians(FLARE))
    middle = along_slope - HANDLE_DROP - HANDLE_HEIGHT / 2      # along the wall's slope
    z = middle * math.cos(math.radians(FLARE))
    mid_wall = TRAY.half_x + middle * math.sin(math.radians(FLARE)) + 0.005
    for sign in (1.0, -1.0):
        assert not _inside_a_solid(TRAY, (sign * mid_wall, 0.0, z))        # the hole
        assert _inside_a_solid(TRAY, (sign * mid_wall, 0.1, z))            # wall beside it
    # The long (y) walls have none.
    assert _inside_a_solid(TRAY, (0.0, TRAY.half_y + z * RUN + 0.005, z))
    plain = fixture_from_record({**TRAY.to_record(), "handle_holes": False})
    assert _inside_a_solid(plain, (mid_wall, 0.0, z))


def test_the_renderer_draws_the_same_walls_as_pybullets_ray_test():
    """The renderer places turned solids with ``euler_rotation`` under the fixture's yaw
    (``render.scene_boxes``), the independent set with pybullet's own quaternions
    (``independent.RayWorld``): per pixel, both must hit the fixture in the same places, for
    a tote turned and moved off the origin."""
    pytest.importorskip("pybullet")
    from training.independent import RayWorld

    placed = replace(TRAY, x=0.12, y=-0.07, yaw=0.7, base_z=0.01)
    episode = {"fixture": placed.to_record(), "objects": []}
    pos = np.array([0.8, -0.5, 0.66])
    cam = Camera(96, 72, 80.0, 80.0, 47.5, 35.5, pos, look_at(pos, np.array([0.12, -0.07, 0])))
    room_floor = placed.room_floor_z
    depth, labels, _ = render(scene_boxes(episode, [], SceneConfig(), DEFAULT_TABLE),
                              room_floor, cam)
    world = RayWorld()
    try:
        bodies = world.build(episode, [], SceneConfig(), DEFAULT_TABLE)
        view = {"width": 96, "height": 72, "fx": 80.0, "fy": 80.0, "cx": 47.5, "cy": 35.5,
                "position": pos.tolist(), "rotation": cam.rotation.tolist()}
        _, theirs, _ = world.cast(view, bodies)
    finally:
        world.close()
    ours = labels == FIXTURE
    assert (theirs == FIXTURE).sum() > 1500
    assert np.mean(ours == (theirs == FIXTURE)) > 0.995       # all but silhouette pixels


@pytest.mark.parametrize("where,size,expected", [
    # Wedged against the leaning wall, beyond the base's footprint but inside the box.
    ((0.3 + 0.12 * RUN - 0.017, 0.0, 0.15), 0.03, "inside"),
    # On the table against the wall's outside, under the opening's edge.
    ((0.36, 0.0, 0.03), 0.06, "outside"),
    # Resting on the lip.
    ((0.3 + 0.2 * RUN + 0.025, 0.0, 0.23), 0.06, "partly_inside"),
], ids=["wedged-inside", "outside-under-lean", "on-lip"])
def test_measurements_follow_the_leaning_walls_and_the_lip(where, size, expected):
    obj = {"shape": "box", "size": [size] * 3, "position": list(where),
           "orientation": [0.0, 0.0, 0.0, 1.0]}
    episode = {"fixture": TRAY.to_record(), "objects": [obj]}
    measured = object_measurements(obj, episode, SceneConfig())
    assert geometric_outcome(measured) == expected, measured


def test_the_tote_spec_draws_plain_and_leaning_walls_lips_and_holes_that_fit_their_table():
    scene = load_scene("tote").scene
    rng = np.random.default_rng(3)
    flares, lips, holes, plain = [], [], [], []
    for _ in range(300):
        fixture = draw_fixture(scene, float(rng.uniform(-1.5, 1.5)), 0.0, rng)
        plain.append(fixture.flare_deg == fixture.lip_width == 0 and not fixture.handle_holes)
        if not plain[-1]:
            flares.append(fixture.flare_deg)
            lips.append(fixture.lip_width)
            holes.append(fixture.handle_holes)
        assert fixture_from_record(fixture.to_record()) == fixture
        # Its outer footprint stays on the table, wherever on it the tote stands.
        reach = fixture.outer_half_footprint()
        table = fixture.table
        c, s = math.cos(fixture.yaw), math.sin(fixture.yaw)
        offset = np.array([[c, s], [-s, c]]) @ np.array([fixture.x - table.x,
                                                        fixture.y - table.y])
        assert np.all(np.abs(offset) + reach <= [table.half_x, table.half_y])
    assert 0.0 <= min(flares) < 2.0 and 18.0 < max(flares) <= 20.0
    assert 0.0 <= min(lips) and max(lips) <= 0.03
    assert 0.4 < np.mean(holes) < 0.6
    assert 0.22 < np.mean(plain) < 0.38           # plain_wall_share: the old spec's totes


@pytest.mark.parametrize("fields,error", [
    ({"wall_flare_deg": [0.0, 40.0]}, "wall_flare_deg"),
    ({"lip_width": [0.0, 0.5]}, "lip_width"),
    ({"handle_hole_share": 1.5}, "handle_hole_share"),
    ({"plain_wall_share": -0.1}, "plain_wall_share"),
    ({"fixture": "board", "plain_wall_share": 0.3}, "a board has none"),
    ({"fixture": "board", "wall_flare_deg": [0.0, 5.0]}, "a board has none"),
])
def test_bad_wall_fields_are_refused(fields, error):
    with pytest.raises(ConfigError, match=error):
        SceneConfig(**{k: tuple(v) if isinstance(v, list) else v
                       for k, v in fields.items()}).validate()


def test_the_physics_keeps_every_solid_of_a_many_piece_fixture():
    """pybullet drops children past 16 in one compound shape; a leaning tote has dozens of
    pieces. Rays from the tote's middle must hit every wall where it is, at every height."""
    pytest.importorskip("pybullet")
    import pybullet as pb

    from training.simulate import World

    assert len(TRAY.solid_boxes()) > 16
    world = World(SceneConfig())
    try:
        world._build(TRAY)
        c = world.client
        for body in world.fixture_bodies:
            pb.resetBasePositionAndOrientation(body, [0, 0, 0], [0, 0, 0, 1], physicsClientId=c)
        for z in np.linspace(0.02, 0.17, 6):
            half_x, half_y = TRAY.region().half_at(z)
            ends = [[0, -1, z], [0, 1, z], [-1, 0.15, z], [1, 0.15, z]]
            hits = pb.rayTestBatch([[0, 0, z], [0, 0, z], [0, 0.15, z], [0, 0.15, z]], ends,
                                   physicsClientId=c)
            assert all(h[0] >= 0 for h in hits), z
            reached = [abs(h[3][1]) for h in hits[:2]] + [abs(h[3][0]) for h in hits[2:]]
            assert reached == pytest.approx([half_y, half_y, half_x, half_x], abs=0.004), z
    finally:
        world.close()


def test_no_wall_piece_is_a_sliver():
    """Strip cuts and handle-hole edges never leave a piece thinner than SLIVER up the slope
    (a box of a fraction of a millimetre is not something to hand a physics engine)."""
    from training.fixture import SLIVER

    for flare in np.linspace(0.0, 20.0, 41):
        for height in (0.1, 0.17, 0.23, 0.3):
            tote = fixture_from_record({**TRAY.to_record(), "flare_deg": float(flare),
                                        "wall_height": height})
            solids = tote.solid_boxes()
            rim = 4 if tote.flare_deg or tote.lip_width else 0   # the flat rim comes last
            walls = [half for half, _, _ in solids[1:len(solids) - rim]]
            assert len(walls) >= 4
            assert min(2 * half[2] for half in walls) >= SLIVER - 1e-9, (flare, height)
