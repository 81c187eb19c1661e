"""COLMAP work in a process of its own: `python -m splatcli.sfm.worker JOB` (JOB: a JSON object),
started by sfm/colmap.py. It imports pycolmap alone (no torch), so it starts in a third of a second.

* "match": match and verify a share of the image pairs on one thread, into the job's copy of
  the database, printing a line per call (of `per_call` pairs) done. COLMAP's matcher on several
  threads in one process does not repeat: its threads race, and 2 to 35 of 714 pairs of 40 photos
  came out different in 2 of 6 runs of one machine with nothing else running; on one thread
  it repeats. Processes of one thread each repeat and still use every core.
* "global": COLMAP's global mapper, which pycolmap cannot cancel: a process can be stopped.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

PAIRS_PER_CALL = 100  # the least per call: each reloads descriptors and builds each image's index again
CALLS = 4  # per process: more, smaller calls cost more (1,700 pairs in 2 processes: 45.5 s in calls of 100,
# 42.3 s of 170, 41.8 s of 400)


def match_options(pycolmap: Any, num_threads: int, max_ratio: float, min_inliers: int, seed: int) -> tuple:
    """COLMAP's matching and verification options as splatcli sets them (colmap.MatchOptions)."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = num_threads
    mo.sift.max_ratio = max_ratio
    vo = pycolmap.TwoViewGeometryOptions()
    vo.min_num_inliers = min_inliers
    vo.ransac.random_seed = seed
    return mo, vo


def match_chunk(pycolmap: Any, db: str, pairs: list[list[str]], list_file: str, opts: dict, **call: Any) -> None:
    """Match and verify `pairs` into `db` in one call (`call`: e.g. pycolmap's cancellation token)."""
    mo, vo = match_options(pycolmap, **opts)
    po = pycolmap.ImportedPairingOptions()
    po.match_list_path = list_file
    Path(list_file).write_text("".join(f"{a} {b}\n" for a, b in pairs), encoding="utf-8")
    pycolmap.match_image_pairs(db, matching_options=mo, pairing_options=po, verification_options=vo,
                               device=pycolmap.Device.cpu, **call)


def match(pycolmap: Any, db: str, pairs: list[list[str]], list_file: str, opts: dict, per_call: int) -> None:
    """The "match" job: `pairs` into `db`, `per_call` at a time, a line on stdout after each."""
    for i in range(0, len(pairs), per_call):
        chunk = pairs[i : i + per_call]
        match_chunk(pycolmap, db, chunk, list_file, opts)
        print(len(chunk), flush=True)


def global_map(pycolmap: Any, db: str, images: str, out: str, seed: int, threads: int) -> None:
    """COLMAP's global mapper, each model written under out/<k>."""
    pycolmap.set_random_seed(seed)
    o = pycolmap.GlobalPipelineOptions()
    o.random_seed = o.mapper.random_seed = seed
    o.num_threads = o.mapper.num_threads = threads
    o.mapper.rotation_averaging.random_seed = seed
    o.mapper.global_positioning.random_seed = seed
    o.mapper.retriangulation.random_seed = seed
    o.mapper.global_positioning.use_gpu = False
    o.mapper.bundle_adjustment.ceres.use_gpu = False
    pycolmap.global_mapping(db, images, out, options=o)


def main() -> None:
    job = json.loads(sys.argv[1])
    import pycolmap

    pycolmap.logging.minloglevel = 0 if job.pop("verbose", False) else 3
    kind = job.pop("kind")
    if kind == "match":
        match(pycolmap, **job)
    else:
        global_map(pycolmap, **job)


if __name__ == "__main__":
    main()
