"""`cfrace tournament --ray`: the pairs of a tournament spread over Ray workers.

Each task races a contiguous share of the pairs with cfrace.evaluate.race.tournament_pairs, from
the same start poses (same seed) as the local tournament; the races of one world do not depend on
the other worlds of a batch, so the matrix is the same cell for cell. The policy files (and a track
given as a file) travel with the tasks, so the workers of a cluster need cfrace but not the files.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Callable

from cfrace.evaluate.race import tournament_pairs


def split(items: list, parts: int) -> list[list]:
    """``items`` in at most ``parts`` contiguous chunks of near-equal size (none empty)."""
    parts = max(1, min(parts, len(items)))
    q, r = divmod(len(items), parts)
    out, k = [], 0
    for p in range(parts):
        n = q + (1 if p < r else 0)
        out.append(items[k:k + n])
        k += n
    return out


def _pairs_task(blobs: list[tuple[str, bytes]], track: str, track_blob: bytes | None, *args) -> list[dict]:
    """On a worker: write the policies (and track) to a temporary folder, race the pairs there."""
    with tempfile.TemporaryDirectory(prefix="cfrace-tournament-") as tmp:
        paths = []
        for name, data in blobs:
            p = Path(tmp) / name
            p.write_bytes(data)
            paths.append(str(p))
        if track_blob is not None:
            t = Path(tmp) / "track" / Path(track).name
            t.parent.mkdir()
            t.write_bytes(track_blob)
            track = str(t)
        return tournament_pairs(paths, track, *args)


def ray_pair_runner(address: str | None = None, cpus: int | None = None, tasks: int | None = None) -> Callable:
    """A ``pair_runner`` for cfrace.evaluate.race.tournament: one Ray task per CPU of the cluster
    (or ``tasks``), each a share of the pairs, one simulator thread each."""
    from cfrace.sweep.ray_exec import init_ray

    def run(paths, track_name, obstacles, races, laps, seed, limit, profile, threads, pairs) -> list[dict]:
        ray = init_ray(address, cpus)
        n = tasks or int(ray.cluster_resources().get("CPU", 1))
        task = ray.remote(num_cpus=threads or 1, max_retries=1)(_pairs_task)
        blobs = [(f"{k}_{Path(p).name}", Path(p).read_bytes()) for k, p in enumerate(paths)]
        track_path = Path(track_name)
        track_blob = track_path.read_bytes() if track_path.is_file() else None
        refs = [task.remote(blobs, track_name, track_blob, obstacles, races, laps, seed, limit, profile, threads,
                            chunk) for chunk in split(pairs, n)]
        return [row for rows in ray.get(refs) for row in rows]

    return run
