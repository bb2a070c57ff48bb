"""The offline dataset pipeline end to end: simulate -> discover -> render -> manifest -> cache.

Small real runs of ``python -m training`` (subprocesses, the way people run it) are shared by the
whole module: 40 episodes with one worker, the same with two workers, and 400 episodes of
simulation + discovery. Everything else is checked on them or with pure functions.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from task_outcome_ros.labels import (
    BACKGROUND,
    DEFAULT_TABLE,
    FIXTURE,
    IGNORE,
    outcome_pixel_counts,
    outcomes_present,
)
from training.chunks import load_chunks
from training.config import (
    DatasetConfig,
    DiscoverConfig,
    SceneConfig,
    dataset_config_from_dict,
    load_json,
)
from training.dataset import manifest_table, split_episodes
from training.discover import describe_cluster, features, table_of
from training.evaluate import evaluate
from training.fixture import episode_fixture
from training.geometry import SAMPLE_GRID, geometric_outcome, object_measurements
from training.hard_cases import run_episodes
from training.render import draw_camera, read_pair, render, render_episode, scene_boxes
from training.rest_place import BENEATH_SUPPORT, BOTH, ON_SUPPORT, places_of
from training.scene import load_scene
from training.seeding import episode_rng

# The default task's outcome ids (docs/interface.md §3).
SUCCESS, FELL_OUTSIDE, STUCK_ON_RIM = (DEFAULT_TABLE.outcome_ids[name] for name in
                                      DEFAULT_TABLE.outcome_names)


task_word = DiscoverConfig().outcome_name  # descriptor -> the default task's word

pytestmark = pytest.mark.pipeline

REPO = Path(__file__).resolve().parents[1]
SEED = 7
EPISODES = 40
CHUNK = 5            # 8 chunks per stage: a wide window to interrupt the resumable run
SMALL = ["--episodes", str(EPISODES), "--chunk-size", str(CHUNK), "--seed", str(SEED)]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TOL = 1e-4           # m: rendered depth vs exact geometry


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    result = subprocess.run([sys.executable, "-m", "training", *args], cwd=REPO,
                            capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"python -m training {' '.join(args)}:\n{result.stderr}"
    return result


def _files(run: Path) -> dict[str, Path]:
    return {str(p.relative_to(run)): p for p in sorted(run.rglob("*")) if p.is_file()}


def _assert_same_bytes(a: Path, b: Path, skip: tuple[str, ...] = ("timings.json",)) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    differ = [name for name in fa if name not in skip
              and fa[name].read_bytes() != fb[name].read_bytes()]
    assert not differ, f"{len(differ)} files differ between {a} and {b}: {differ[:10]}"


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The same small dataset generated with one and with two workers."""
    base = tmp_path_factory.mktemp("dataset")
    out = {}
    for workers in (1, 2):
        out[f"w{workers}"] = base / f"w{workers}"
        _cli("dataset", *SMALL, "--workers", str(workers), "--out", str(out[f"w{workers}"]))
    return out


@pytest.fixture(scope="module")
def run(runs) -> Path:
    return runs["w1"]


@pytest.fixture(scope="module")
def run_data(run) -> dict:
    cfg, episodes, outcomes = _load_run(run)
    return {"cfg": cfg, "episodes": episodes, "outcomes": outcomes,
            "manifest": load_json(run / "manifest.json")}


# ---- determinism and resumption -------------------------------------------------------------

def test_worker_count_does_not_change_a_byte(runs):
    w1, w2 = runs["w1"], runs["w2"]
    names = _files(w1)
    assert sum(n.startswith("images/") and n.endswith(".png") for n in names) == 2 * EPISODES
    for stage in ("simulate", "render"):
        assert sum(n.startswith(f"{stage}/chunk_") for n in names) == EPISODES // CHUNK
    for report in ("manifest.json", "discovery.json", "outcomes.json", "discovery.png",
                   "examples.png", "noise.png"):
        assert report in names
    _assert_same_bytes(w1, w2, skip=("timings.json", "config.json"))
    c1, c2 = load_json(w1 / "config.json"), load_json(w2 / "config.json")
    assert (c1.pop("workers"), c2.pop("workers")) == (1, 2)
    assert c1 == c2
    # The manifest carries the run's config, minus the worker count (not a data parameter).
    assert load_json(w1 / "manifest.json")["config"] == c1
    assert dataset_config_from_dict(c1) == load_scene("default", episodes=EPISODES, seed=SEED,
                                                      chunk_size=CHUNK)


def test_the_tote_spec_is_deterministic_and_labels_its_own_scene(tmp_path):
    """Same seed, same bytes, whatever the worker count, for a spec that draws its fixture,
    table and shapes per episode; the labels sit on the objects the geometry says."""
    runs = {}
    for workers in (1, 2):
        runs[workers] = tmp_path / f"tote_w{workers}"
        _cli("dataset", "--scene", "tote", "--episodes", "8", "--chunk-size", "4", "--seed",
             "2", "--workers", str(workers), "--out", str(runs[workers]))
    _assert_same_bytes(runs[1], runs[2], skip=("timings.json", "config.json"))
    cfg, episodes, outcomes = _load_run(runs[1])
    assert cfg.task == "tote" and cfg.scene.table_size is not None
    shapes = {o["shape"] for e in episodes for o in e["objects"]}
    sizes = {(e["fixture"]["half_x"], e["fixture"]["half_y"]) for e in episodes}
    assert len(sizes) == len(episodes)  # a footprint of its own per episode
    for e in episodes:
        f = e["fixture"]
        assert 0.15 <= f["half_x"] <= 0.40 and 0.125 <= f["half_y"] <= 0.30
        assert 0.10 <= f["wall_height"] <= 0.30 and f["table"] is not None
    manifest = load_json(runs[1] / "manifest.json")
    # Eight episodes need not show every outcome: the ids are the run's own table's.
    table = manifest_table(manifest)
    assert table == table_of(load_json(runs[1] / "discovery.json"))
    for im, names in zip(manifest["images"], outcomes):
        _, labels = read_pair(runs[1], im["episode"])
        # Only the episode's own outcomes are painted (plus background, fixture, no depth).
        allowed = {0, 1, 255} | {table.outcome_ids[name] for name in names}
        assert set(np.unique(labels).tolist()) <= allowed, (im["episode"], names)
        assert im["present"] == outcomes_present(labels, table=table)
    assert shapes <= {"box", "cylinder"}
    _assert_places_follow_the_final_heights(runs[1], cfg, episodes, outcomes)


def _assert_places_follow_the_final_heights(run_dir, cfg, episodes, outcomes):
    """The evaluation's places on a real tote run: an outcome with an object lying on the room
    floor (within 0.3 m of it; tables are 0.7-0.8 m high) rests beneath the support or both,
    one with an object near the table top on it or both; a success, in the tote, on it.
    Then `evaluate` reports recall by place for every present outcome."""
    run = run_episodes(run_dir, set(range(len(episodes))))
    places = places_of(run, run_dir)
    assert set(places) == set(range(len(episodes)))
    on_floor = 0
    for episode, names in zip(episodes, outcomes):
        table = episode_fixture(episode, cfg.scene).table
        found = places[episode["episode"]]
        assert set(found) == set(names) and found.get("success", ON_SUPPORT) == ON_SUPPORT
        for obj, name in zip(episode["objects"], names):
            z = obj["position"][2]
            if z < table.floor_z + 0.3:
                on_floor += 1
                assert found[name] in (BENEATH_SUPPORT, BOTH), (episode["episode"], name)
            elif z > table.top_z - 0.1:
                assert found[name] in (ON_SUPPORT, BOTH), (episode["episode"], name)
    assert on_floor > 0, "the seed must put a fallen object on the room floor"
    report = evaluate("tote", run_dir, "all", run_dir / "eval", progress=False)
    truth = [im["present"] for im in load_json(run_dir / "manifest.json")["images"]]
    for name, by_place in report["recall_by_place"]["by_outcome"].items():
        counted = sum(e["images"] for bins in by_place.values() for e in bins)
        assert counted == sum(p.get(name, False) for p in truth), name  # each present once


def test_the_shelf_spec_runs_end_to_end_with_its_own_label_table(tmp_path):
    """A second task from its spec alone: boards on legs or walls, placed objects, the
    discovered outcomes under the shelf's words, labels painted with the run's own ids and the
    board in every image."""
    out = tmp_path / "shelf"
    _cli("dataset", "--scene", "shelf", "--episodes", "12", "--chunk-size", "6", "--seed", "3",
         "--out", str(out))
    cfg, episodes, outcomes = _load_run(out)
    assert cfg.task == "shelf" and {e["fixture"]["kind"] for e in episodes} == {"board"}
    assert {e["fixture"]["wall_mounted"] for e in episodes} == {True, False}
    table = manifest_table(load_json(out / "manifest.json"))
    assert table.classes[:2] == ("background", "shelf")
    assert set(table.outcome_names) <= {"on_shelf", "fell_off", "hanging_over_edge"}
    assert {name for names in outcomes for name in names} == set(table.outcome_names)
    for im, names in zip(load_json(out / "manifest.json")["images"], outcomes):
        _, labels = read_pair(out, im["episode"])
        assert (labels == FIXTURE).sum() > 500, im["episode"]  # the board is in view
        allowed = {0, 1, 255} | {table.outcome_ids[name] for name in names}
        assert set(np.unique(labels).tolist()) <= allowed, (im["episode"], names)


def test_killed_run_resumes_to_identical_bytes(runs, tmp_path):
    """SIGKILL the whole process group mid-render, leave stray temp files, run again."""
    out = tmp_path / "resumed"
    cmd = [sys.executable, "-m", "training", "dataset", *SMALL, "--workers", "2",
           "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    render_dir = out / "render"
    deadline = time.monotonic() + 240
    try:
        while not list(render_dir.glob("chunk_*.json")):
            assert proc.poll() is None, "the run ended before the render stage could be killed"
            assert time.monotonic() < deadline, "no render chunk appeared in time"
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    done = {p.name: p.stat().st_mtime_ns for p in render_dir.glob("chunk_*.json")}
    assert 1 <= len(done) < EPISODES // CHUNK, "killed too late to test resumption"
    assert not (out / "manifest.json").exists()
    # Temp files an interrupted atomic write can leave behind; the resume must not trip on them.
    (render_dir / f"chunk_{EPISODES - CHUNK:07d}.json.tmp").write_text('{"episodes": [')
    (out / "images" / f"{EPISODES - 1:06d}_depth.tmp.png").write_bytes(b"\x89PNG torn")
    (out / "simulate" / "chunk_0000000.json.tmp").write_text("{")

    _cli(*cmd[3:])
    resumed = {p.name: p.stat().st_mtime_ns for p in render_dir.glob("chunk_*.json")}
    assert len(resumed) == EPISODES // CHUNK
    assert all(resumed[name] == mtime for name, mtime in done.items()), \
        "chunks finished before the kill were recomputed instead of reused"
    for stray in out.rglob("*.tmp*"):
        stray.unlink()
    _assert_same_bytes(out, runs["w2"])


# ---- discovery -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def discovery_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("discovery")
    _cli("simulate", "--episodes", "400", "--chunk-size", "100", "--workers", "2",
         "--seed", "3", "--out", str(out))
    _cli("discover", "--out", str(out))
    return out


def test_discovery_finds_the_three_outcomes(discovery_run):
    report = load_json(discovery_run / "discovery.json")
    for key in ("n_episodes", "n_clusters", "cluster_names", "ari_vs_geometry", "noise_points"):
        assert key in report, f"docs/interface.md §6 key {key} missing from discovery.json"
    assert report["n_episodes"] == 400
    assert report["n_clusters"] == 3
    sizes = report["cluster_names"]
    assert set(sizes) == set(DEFAULT_TABLE.outcome_names)
    assert all(sizes[name] > 0 for name in DEFAULT_TABLE.outcome_names), sizes
    assert max(sizes, key=sizes.get) == "success"
    assert sum(sizes.values()) == report["n_objects"]
    assert report["ari_vs_geometry"] >= 0.95
    assert isinstance(report["noise_points"], int) and 0 <= report["noise_points"]
    # docs/interface.md §2: ~51-60 % success, 30-35 % outside, 10-16 % stuck (wide bounds:
    # ~1000 objects)
    frac = {k: v / report["n_objects"] for k, v in sizes.items()}
    assert 0.45 <= frac["success"] <= 0.70, frac
    assert 0.20 <= frac["fell_outside"] <= 0.45, frac
    assert 0.03 <= frac["stuck_on_rim"] <= 0.20, frac
    outcomes = load_json(discovery_run / "outcomes.json")["outcomes"]
    episodes = load_chunks(discovery_run / "simulate", 400, 100)
    assert [len(o) for o in outcomes] == [len(e["objects"]) for e in episodes]


def test_one_grid_point_outside_is_farther_than_eps_from_fully_inside():
    """The gap discovery relies on: a box poking out of the container by one sample point is
    not within DBSCAN's eps of the fully-inside spike, so it cannot chain into success."""
    base = {"com_beyond_edge": -5.0}
    inside, one_out = features([{**base, "inside_fraction": 1.0},
                                {**base, "inside_fraction": 1.0 - 1.0 / SAMPLE_GRID**3}])
    assert inside[1] == 0.0
    assert one_out[1] - inside[1] > 3 * DiscoverConfig().eps
    assert features([{**base, "inside_fraction": 0.0}])[0, 1] == pytest.approx(1.0, abs=1e-3)


def test_success_objects_are_entirely_inside(discovery_run):
    """No object that sticks out of the container by any amount is discovered as a success."""
    cfg = dataset_config_from_dict(load_json(discovery_run / "config.json"))
    outcomes = load_json(discovery_run / "outcomes.json")["outcomes"]
    episodes = load_chunks(discovery_run / "simulate", 400, 100)
    poking_out = [(e["episode"], k) for e, names in zip(episodes, outcomes)
                  for k, (obj, name) in enumerate(zip(e["objects"], names))
                  if name == "success"
                  and object_measurements(obj, e, cfg.scene)["inside_fraction"] < 1.0]
    assert poking_out == []


def _assert_png(path: Path) -> None:
    assert path.read_bytes()[:8] == PNG_MAGIC, f"{path} is not a PNG"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.ndim == 3 and min(image.shape[:2]) >= 100, path


def test_run_writes_its_figures(discovery_run, run):
    _assert_png(discovery_run / "discovery.png")
    for name in ("discovery.png", "examples.png", "noise.png"):
        _assert_png(run / name)


def _box(size, position, orientation=(0.0, 0.0, 0.0, 1.0)) -> dict:
    return {"size": list(size), "position": list(position), "orientation": list(orientation)}


SCENE = SceneConfig()
FLAT = {"container_yaw": 0.0, "floor_z": 0.0}
BOTTOM = SCENE.bottom_thickness
# Hand-made final states (container at the origin, yaw 0, floor at z = 0).
IN_MIDDLE = _box((0.2, 0.15, 0.1), (0.05, -0.1, BOTTOM + 0.05))
OUTSIDE = _box((0.2, 0.15, 0.1), (0.9, 0.3, 0.05))
UPRIGHT_TALL = _box((0.1, 0.1, 0.3), (0.0, 0.0, BOTTOM + 0.15))         # top 0.07 above rim
ON_THE_WALL = _box((0.2, 0.2, 0.1), (0.51, 0.0, SCENE.wall_height[1] + 0.05))


@pytest.mark.parametrize("obj,expected", [(IN_MIDDLE, "success"), (OUTSIDE, "fell_outside"),
                                          (UPRIGHT_TALL, "stuck_on_rim"),
                                          (ON_THE_WALL, "stuck_on_rim")],
                         ids=["middle", "outside", "upright-tall", "on-wall"])
def test_geometric_outcome_of_hand_made_states(obj, expected):
    m = object_measurements(obj, FLAT, SCENE)
    assert task_word(geometric_outcome(m)) == expected
    if expected == "success":
        assert m["inside_fraction"] == 1.0 and m["top_above_region"] < 0
    if expected == "fell_outside":
        assert m["inside_fraction"] == 0.0 and m["com_offset"] > 1.04
    if obj is UPRIGHT_TALL:
        assert m["top_above_region"] == pytest.approx(0.07)


def test_geometry_uses_the_container_frame():
    """(0.65, 0) is outside an unrotated container, but inside one turned by 45 degrees
    (Chebyshev distance 0.46) and its floor height moves with the container."""
    obj = _box((0.1, 0.1, 0.1), (0.65, 0.0, 0.3 + BOTTOM + 0.05))
    raised = {"container_yaw": 0.0, "floor_z": 0.3}
    assert task_word(geometric_outcome(object_measurements(obj, raised, SCENE))) == "fell_outside"
    turned = {"container_yaw": np.pi / 4, "floor_z": 0.3}
    m = object_measurements(obj, turned, SCENE)
    assert m["com_offset"] == pytest.approx(0.65 / np.sqrt(2) / 0.5)
    assert task_word(geometric_outcome(m)) == "success"


def test_name_cluster_names_from_geometry():
    rng = np.random.default_rng(0)

    def members(obj: dict, n: int = 15, jitter: float = 0.03) -> list[dict]:
        out = []
        for _ in range(n):
            moved = dict(obj, position=list(np.add(obj["position"],
                                                   [*rng.uniform(-jitter, jitter, 2), 0])))
            out.append(object_measurements(moved, FLAT, SCENE))
        return out

    assert task_word(describe_cluster(members(IN_MIDDLE))) == "success"
    assert task_word(describe_cluster(members(OUTSIDE))) == "fell_outside"
    assert task_word(describe_cluster(members(UPRIGHT_TALL))) == "stuck_on_rim"
    assert task_word(describe_cluster(members(ON_THE_WALL, jitter=0.005))) == "stuck_on_rim"
    # A cluster is named by its typical member, not by a stray one.
    mostly_inside = members(IN_MIDDLE, 12) + members(OUTSIDE, 3)
    assert task_word(describe_cluster(mostly_inside)) == "success"


# ---- labels and depth agree with the 3-D scene ----------------------------------------------

def _rays(cam) -> np.ndarray:
    """(H, W, 3) world ray of every pixel with unit optical-axis component (float64)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    local = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    return local @ np.asarray(cam.rotation, np.float64).T


def _box_distance(points: np.ndarray, box) -> np.ndarray:
    """Signed distance of points (N, 3) to a box's surface (negative inside)."""
    q = np.abs((points - box.centre) @ box.rotation) - box.half_extents
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _first_hit(origin: np.ndarray, rays: np.ndarray, box) -> np.ndarray:
    """Independent float64 slab test: ray parameter of the first hit, inf if none."""
    o = (origin - box.centre) @ box.rotation
    d = rays @ box.rotation
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-box.half_extents - o) / d, (box.half_extents - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((t_far >= t_near) & (t_near > 0.05), t_near, np.inf)


def _load_run(run: Path) -> tuple[DatasetConfig, list[dict], list[list[str]]]:
    cfg = dataset_config_from_dict(load_json(run / "config.json"))
    return (cfg, load_chunks(run / "simulate", cfg.episodes, cfg.chunk_size),
            load_json(run / "outcomes.json")["outcomes"])


def _shots(cfg: DatasetConfig, episodes: list[dict], outcomes: list[list[str]],
           chosen: list[int]) -> list[dict]:
    out = []
    for i in chosen:
        ep = episodes[i]
        fixture = episode_fixture(ep, cfg.scene)
        cam, _ = draw_camera(cfg.camera, fixture, episode_rng(cfg.seed, i, "render"))
        boxes = scene_boxes(ep, outcomes[i], cfg.scene, DEFAULT_TABLE)
        depth, labels, cosine = render(boxes, fixture.room_floor_z, cam)
        out.append({"index": i, "episode": ep, "camera": cam, "boxes": boxes, "depth": depth,
                    "labels": labels, "cosine": cosine,
                    # whole, as rendered above, even where the spec empties the frame
                    "noisy": render_episode(ep, outcomes[i], cfg, cfg.seed, DEFAULT_TABLE,
                                            emptied=False)})
    return out


@pytest.fixture(scope="module")
def shots(discovery_run) -> list[dict]:
    """Episodes of the 400-episode run whose objects cover all three outcomes (a 40-episode
    run may have too few stuck objects for a cluster of their own), rendered clean and noisy."""
    cfg, episodes, outcomes = _load_run(discovery_run)
    chosen, seen = [], set()
    for i, names in enumerate(outcomes):
        if set(names) - seen or len(chosen) < 2:
            chosen.append(i)
            seen |= set(names)
        if seen == set(DEFAULT_TABLE.outcome_names) and len(chosen) >= 3:
            break
    assert seen == set(DEFAULT_TABLE.outcome_names)
    return _shots(cfg, episodes, outcomes, chosen)


@pytest.fixture(scope="module")
def stored_shots(run) -> list[dict]:
    """The first episodes of the small rendered run, rendered again in-process."""
    return _shots(*_load_run(run), chosen=[0, 1, 2])


def test_clean_depth_lies_on_the_labelled_surface(shots):
    """Back-projected pixels of every class lie on a surface of that class.

    Measured error is < 1 um (float32 depth); the 0.1 mm bound still catches a half-pixel slip
    in the pixel-centre convention (~1-2 mm on slanted surfaces at 2 m)."""
    labelled = set()
    for shot in shots:
        cam, depth, labels = shot["camera"], shot["depth"], shot["labels"]
        points = cam.position + depth[..., None].astype(np.float64) * _rays(cam)
        assert np.isfinite(depth).all(), "at 40-65 deg elevation every ray meets the floor"
        floor = labels == BACKGROUND
        assert np.abs(points[floor][:, 2] - shot["episode"]["floor_z"]).max() < TOL
        for label in np.unique(labels[~floor]):
            boxes = [b for b in shot["boxes"] if b.label == label]
            assert boxes, f"label {label} in the image but no box carries it"
            pts = points[labels == label]
            dist = np.min([np.abs(_box_distance(pts, b)) for b in boxes], axis=0)
            assert dist.max() < TOL, f"episode {shot['index']} label {label}: {dist.max()} m"
            labelled.add(int(label))
        assert (labels == FIXTURE).any()
    assert labelled >= {FIXTURE, *DEFAULT_TABLE.outcome_ids.values()}


def test_clean_render_is_the_nearest_surface(shots):
    """Z-buffering: an independent float64 ray cast (every 4th pixel) finds the same nearest
    surface and label, except for a few grazing silhouette pixels."""
    for shot in shots:
        cam = shot["camera"]
        rays = _rays(cam)[::4, ::4]
        floor_z = shot["episode"]["floor_z"]
        with np.errstate(divide="ignore"):
            t_floor = (floor_z - cam.position[2]) / rays[..., 2]
        best = np.where(t_floor > 0.05, t_floor, np.inf)
        best_label = np.full(best.shape, BACKGROUND, np.uint8)
        for box in shot["boxes"]:
            t = _first_hit(cam.position, rays, box)
            closer = t < best
            best[closer], best_label[closer] = t[closer], box.label
        depth, labels = shot["depth"][::4, ::4], shot["labels"][::4, ::4]
        same_label = labels == best_label
        assert same_label.mean() > 0.999, f"episode {shot['index']}: {(~same_label).sum()}"
        assert np.abs(depth[same_label] - best[same_label]).max() < TOL


def test_noisy_labels_ignore_exactly_the_invalid_depth(shots):
    for shot in shots:
        noisy = shot["noisy"]
        depth, labels = noisy["depth"], noisy["labels"]
        assert depth.dtype == np.float32 and labels.dtype == np.uint8
        assert np.array_equal(labels == IGNORE, np.isnan(depth))
        assert 0.0 < np.isnan(depth).mean() < 0.3
        np.testing.assert_array_equal(noisy["clean"], shot["depth"])
        # Noise moves edges by a pixel or so; it does not relabel the scene.
        valid = labels != IGNORE
        assert (labels[valid] == shot["labels"][valid]).mean() > 0.97
        # The record's presence is that of the noisy labels, counted here by hand: 50 px of
        # an outcome at 640 x 480 (the paper's rule), scaled to this image's area.
        need = 50 * labels.size / (640 * 480)
        by_hand = {name: int(np.count_nonzero(labels == i)) >= round(need)
                   for name, i in DEFAULT_TABLE.outcome_ids.items()}
        assert noisy["record"]["present"] == by_hand
        assert any(by_hand.values())  # the shots hold outcomes: the check compares something


# ---- the manifest and the stored images -----------------------------------------------------

def test_split_is_95_5_and_disjoint_by_episode(run_data):
    manifest = run_data["manifest"]
    n = manifest["n_images"]
    assert n == EPISODES == len(manifest["images"])
    splits = {s: {im["episode"] for im in manifest["images"] if im["split"] == s}
              for s in ("train", "val")}
    assert splits["train"].isdisjoint(splits["val"])
    assert splits["train"] | splits["val"] == set(range(n))
    assert manifest["split_sizes"] == {s: len(v) for s, v in splits.items()}
    assert abs(len(splits["val"]) - 0.05 * n) <= 1
    # The full-size dataset: exactly 9,500 / 500, reproducible from the seed.
    big = split_episodes(10_000, 0.05, seed=0)
    assert (len(big["train"]), len(big["val"])) == (9500, 500)
    assert set(big["train"]).isdisjoint(big["val"])
    assert big == split_episodes(10_000, 0.05, seed=0) != split_episodes(10_000, 0.05, seed=1)


def test_manifest_records_seeds_camera_objects_and_presence(run, run_data):
    cfg, episodes, outcomes = run_data["cfg"], run_data["episodes"], run_data["outcomes"]
    for im in run_data["manifest"]["images"]:
        i = im["episode"]
        assert im["seed"] == {"simulate": [SEED, i, 1], "render": [SEED, i, 2],
                              "noise": [SEED, i, 3]}
        cam = im["camera"]
        assert (cam["width"], cam["height"]) == (640, 480)
        assert 525.0 <= cam["fx"] <= 590.0 and cam["fx"] == cam["fy"]
        assert abs(cam["cx"] - (cam["width"] - 1) / 2) <= 8.0
        assert abs(cam["cy"] - (cam["height"] - 1) / 2) <= 8.0
        assert 1.6 <= cam["distance"] <= 2.4 and 40.0 <= cam["elevation_deg"] <= 65.0
        position, target = np.array(cam["position"]), np.array(cam["look_at"])
        assert np.linalg.norm(position - target) == pytest.approx(cam["distance"])
        centre = [0.0, 0.0, episodes[i]["floor_z"] + cfg.scene.height_scale / 2]
        assert np.linalg.norm(target - centre) <= 0.1 + 1e-9
        # The recorded seed alone reproduces the camera.
        again, _ = draw_camera(cfg.camera, episode_fixture(episodes[i], cfg.scene),
                               np.random.default_rng(im["seed"]["render"]))
        assert again.fx == cam["fx"] and again.cx == cam["cx"]
        np.testing.assert_array_equal(again.position, position)
        assert im["objects"] == outcomes[i]
        assert len(im["objects"]) == len(episodes[i]["objects"])
        assert (run / im["depth"]).is_file() and (run / im["labels"]).is_file()
        _, labels = read_pair(run, i)
        assert im["present"] == outcomes_present(labels)
        assert im["pixel_counts"] == outcome_pixel_counts(labels)


def test_read_pair_round_trips_the_rendered_images(run, stored_shots):
    for shot in stored_shots:
        depth, labels = read_pair(run, shot["index"])
        noisy = shot["noisy"]
        assert depth.dtype == np.float32 and depth.shape == (480, 640)
        np.testing.assert_array_equal(labels, noisy["labels"])
        np.testing.assert_array_equal(np.isnan(depth), np.isnan(noisy["depth"]))
        valid = ~np.isnan(depth)
        assert np.abs(depth[valid] - noisy["depth"][valid]).max() <= 0.0005 + 1e-6
        mm = depth[valid] * 1000.0
        np.testing.assert_allclose(mm, np.rint(mm), atol=1e-3)    # whole millimetres
        raw = cv2.imread(str(run / "images" / f"{shot['index']:06d}_depth.png"),
                         cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and np.array_equal(raw == 0, ~valid)


# ---- the training view ----------------------------------------------------------------------

def test_cache_and_dataset_shapes(run, tmp_path):
    torch = pytest.importorskip("torch", reason="OutcomeDataset needs torch")
    from training.dataset import OutcomeDataset, cache_path, load_cache

    copy = tmp_path / "run"   # the cache is written into the run folder: keep `run` pristine
    shutil.copytree(run, copy)
    size = (160, 120)
    arrays = load_cache(copy, "train", size, workers=1)
    n_train = load_json(copy / "manifest.json")["split_sizes"]["train"]
    assert arrays["depth"].shape == arrays["valid"].shape == arrays["labels"].shape \
        == (n_train, 120, 160)
    assert arrays["depth"].dtype == arrays["valid"].dtype == np.float16
    assert arrays["labels"].dtype == np.uint8
    assert set(np.unique(arrays["labels"]).tolist()) <= {0, 1, 2, 3, 4, IGNORE}
    assert {0, 1}.issubset(np.unique(arrays["labels"]).tolist())
    assert ((arrays["valid"] >= 0) & (arrays["valid"] <= 1)).all()
    assert (arrays["depth"][arrays["valid"] == 0] == 0).all()
    valid_depth = arrays["depth"][arrays["valid"] > 0].astype(np.float32)
    spec = load_scene("default")   # the nearest and farthest any of its sensors measures
    near = min(spec.noise.bounds("min_range")[0], spec.tof.bounds("min_range")[0])
    far = max(spec.noise.bounds("max_range")[1], spec.tof.bounds("max_range")[1])
    assert near <= valid_depth.min() and valid_depth.max() <= far + 0.01  # float16 rounding
    mtime = cache_path(copy, "train", size).stat().st_mtime_ns

    train = OutcomeDataset(copy, "train", size, workers=1)
    assert cache_path(copy, "train", size).stat().st_mtime_ns == mtime, "cache was rebuilt"
    assert len(train) == n_train
    depth, valid, labels = train[0]
    assert depth.shape == valid.shape == labels.shape == (120, 160)
    assert depth.dtype == valid.dtype == torch.float32 and labels.dtype == torch.int64
    val = OutcomeDataset(copy, "val", size, workers=1)
    assert len(val) == EPISODES - n_train
    with pytest.raises(ValueError, match="split"):
        OutcomeDataset(copy, "test", size, workers=1)


def test_downsample_labels_votes_by_area_ignoring_holes():
    from training.dataset import downsample_labels

    labels = np.zeros((480, 640), np.uint8)
    labels[0:4, 0:3] = SUCCESS            # 12 of a 4 x 4 block: success wins the block
    labels[0:4, 3] = IGNORE               # holes do not vote
    labels[4:14, 0:10] = IGNORE           # a region of nothing but holes stays ignored
    labels[100:200, 200:400] = FELL_OUTSIDE     # a large object survives any factor
    small = downsample_labels(labels, (160, 120))
    assert small[0, 0] == SUCCESS and small[1, 0] == IGNORE and small[0, 1] == BACKGROUND
    assert small[30:50, 50:100].min() == small[30:50, 50:100].max() == FELL_OUTSIDE
    # A non-integer factor (10/3) weighs each source pixel by its share of the output pixel.
    odd = downsample_labels(labels, (192, 144))
    assert odd.shape == (144, 192)
    assert odd[0, 0] == SUCCESS and odd[2, 0] == IGNORE
    assert odd[31:59, 61:119].min() == odd[31:59, 61:119].max() == FELL_OUTSIDE
    share = (odd == FELL_OUTSIDE).sum() / odd.size
    assert share == pytest.approx((labels == FELL_OUTSIDE).sum() / labels.size, rel=0.03)
    assert np.array_equal(downsample_labels(labels, (640, 480)), labels)


# ---- memory and import boundaries -----------------------------------------------------------

MEMORY_PROBE = """
import json, sys
import training.simulate as S
from training.config import SceneConfig
if len(sys.argv) > 1:
    S.REBUILD_EVERY = int(sys.argv[1])
world = S.World(SceneConfig())
peak = {}
for i in range(900):
    S.simulate_episode(world, 11, i)
    if i + 1 in (100, 300, 600, 900):
        with open('/proc/self/status') as status:
            peak[i + 1] = int(next(ln for ln in status if ln.startswith('VmHWM')).split()[1])
print(json.dumps(peak))
"""


def _peak_rss(*args: str) -> dict[int, int]:
    if not Path("/proc/self/status").exists():
        pytest.skip("peak RSS is read from /proc/self/status (Linux only)")
    result = subprocess.run([sys.executable, "-c", MEMORY_PROBE, *args], cwd=REPO,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    return {int(k): v for k, v in json.loads(result.stdout.strip().splitlines()[-1]).items()}


def test_simulation_memory_stays_flat():
    """900 episodes in one World, in a fresh process; peak RSS sampled at episodes 100-900.

    pybullet keeps every box shape ever created (~8 KiB an episode); the World rebuilds itself
    every REBUILD_EVERY episodes to free them. Once the first rebuild cycle is over the peak
    must not move; the leak would add ~5 MiB between episodes 300 and 900 (a 100 -> 600 bound
    of 5 MiB alone would not catch it). The peak is VmHWM, the address space's own high-water
    mark: ru_maxrss would do on a shell-started process, but Linux carries it over from the
    parent across fork + exec, so under pytest it would read pytest's peak and never move.
    """
    peak = _peak_rss()
    assert peak[600] - peak[100] < 5 * 1024, peak
    assert peak[900] - peak[300] < 1.5 * 1024, peak


@pytest.mark.slow
def test_memory_probe_detects_the_leak_without_rebuilds():
    """Control for the test above: with rebuilds disabled the same probe sees the leak."""
    peak = _peak_rss("1000000000")
    assert peak[900] - peak[300] > 3 * 1024, peak


def test_training_modules_import_without_rclpy():
    """Everything in training/ imports with rclpy blocked (the task_outcome_ros core is
    covered by test_node.py::test_package_imports_without_rclpy)."""
    code = (
        "import importlib, json, pkgutil, sys\n"
        "sys.modules['rclpy'] = None\n"          # `import rclpy` now raises ImportError
        "try:\n"
        "    import rclpy\n"
        "    raise SystemExit('the rclpy block does not work')\n"
        "except ImportError:\n"
        "    pass\n"
        "import training\n"
        "names = sorted('training.' + m.name for m in pkgutil.iter_modules(training.__path__))\n"
        "for name in names:\n"
        "    importlib.import_module(name)\n"
        "ros = sorted(m for m in sys.modules if m.startswith(('rclpy.', 'rosidl', 'rcl_')))\n"
        "print(json.dumps({'modules': names, 'ros': ros}))\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    on_disk = {f"training.{p.stem}" for p in (REPO / "training").glob("*.py")
               if p.stem != "__init__"}
    assert set(report["modules"]) == on_disk
    assert report["ros"] == []


def test_default_dataset_config_is_what_the_small_runs_used(run_data):
    """The runs above differ from the default spec only in the CLI options given."""
    cfg, spec = run_data["cfg"], load_scene("default")
    assert (cfg.scene, cfg.camera, cfg.noise, cfg.tof) == (spec.scene, spec.camera, spec.noise,
                                                           spec.tof)
    assert (cfg.episodes, cfg.chunk_size, cfg.seed, cfg.workers) == (EPISODES, CHUNK, SEED, 1)
