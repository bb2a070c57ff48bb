"""Resumable, parallel, deterministic execution of a stage over chunks of episodes.

A stage's work is split into chunks of consecutive episodes. Each chunk is computed by a pure
function of (config, chunk) in a worker process and its outputs are written atomically; the
chunk's own JSON file is written last and marks it complete. Running a stage again skips
complete chunks, so an interrupted run (killed worker, Ctrl-C) resumes where it stopped, and
because every episode is seeded from (run seed, episode index) the bytes do not depend on the
worker count, the chunk order or on interruptions.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from tqdm import tqdm

from training.config import load_json, save_json


def chunk_ranges(n_episodes: int, chunk_size: int) -> list[tuple[int, int]]:
    return [(s, min(s + chunk_size, n_episodes)) for s in range(0, n_episodes, chunk_size)]


def chunk_path(stage_dir: Path, start: int) -> Path:
    return Path(stage_dir) / f"chunk_{start:07d}.json"


def run_chunks(stage_dir: Path, n_episodes: int, chunk_size: int, workers: int,
               work: Callable[[tuple[int, int]], Any], desc: str,
               initializer: Callable[..., None] | None = None, initargs: tuple = ()) -> None:
    """Compute every missing chunk with ``work((start, stop)) -> JSON-able`` and save it.

    ``work`` may write other files (images) before returning; the chunk JSON is saved after.
    """
    stage_dir = Path(stage_dir)
    stage_dir.mkdir(parents=True, exist_ok=True)
    todo = [r for r in chunk_ranges(n_episodes, chunk_size)
            if not chunk_path(stage_dir, r[0]).exists()]
    done_episodes = n_episodes - sum(b - a for a, b in todo)
    bar = tqdm(total=n_episodes, initial=done_episodes, desc=desc, unit="ep",
               dynamic_ncols=True, mininterval=1.0)
    try:
        for (start, _), result in _imap(work, todo, workers, initializer, initargs):
            save_json(chunk_path(stage_dir, start), result)
            bar.update(len(result["episodes"]))
    finally:
        bar.close()


def _imap(work: Callable, todo: list[tuple[int, int]], workers: int,
          initializer: Callable | None, initargs: tuple) -> Iterator[tuple[tuple[int, int], Any]]:
    if not todo:
        return
    if workers <= 1 or len(todo) == 1:
        if initializer is not None:
            initializer(*initargs)
        for r in todo:
            yield r, work(r)
        return
    # spawn: workers start clean (no inherited pybullet/torch threads), same on every OS.
    ctx = mp.get_context("spawn")
    with ctx.Pool(min(workers, len(todo)), initializer=initializer, initargs=initargs) as pool:
        yield from zip(todo, pool.imap(work, todo))


def load_chunks(stage_dir: Path, n_episodes: int, chunk_size: int) -> list[dict]:
    """All episodes of a complete stage, in episode order; a clear error if some are missing."""
    episodes: list[dict] = []
    for start, stop in chunk_ranges(n_episodes, chunk_size):
        path = chunk_path(stage_dir, start)
        if not path.exists():
            raise FileNotFoundError(
                f"{path} is missing: the stage that writes {Path(stage_dir).name}/ did not finish;"
                " run it again to resume")
        data = load_json(path)
        if len(data["episodes"]) != stop - start:
            raise ValueError(f"{path}: expected {stop - start} episodes, found "
                             f"{len(data['episodes'])}")
        episodes.extend(data["episodes"])
    return episodes
