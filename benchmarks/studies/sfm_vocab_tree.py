"""Sequential matching with loop detection through a vocabulary tree built from the survey's own descriptors, against
the SfM stage's quadratic overlap: seconds and pairs, on a copy of a stage's database (features kept, matches cleared).

    .venv/bin/python benchmarks/studies/sfm_vocab_tree.py WS/01_sfm/database.db [--words 4096] [--per-image 300]
        [--overlap 5] [--loop-images 5] [--min-index-distance 6] [--out /tmp/sfm_vocab_tree]

The tree (``pycolmap.VisualIndex.build``, ``--words`` visual words) is trained on ``--per-image`` descriptors drawn
from every image; then ``pycolmap.match_sequential`` matches each image with the next ``--overlap`` images and, through
the tree, with its ``--loop-images`` most similar images at least ``--min-index-distance`` away. Prints the tree's
build time, the matching time and the pairs stored.
"""

from __future__ import annotations

import argparse
import shutil
import sqlite3
import time
from pathlib import Path

import numpy as np


def cleared_copy(database: Path, out: Path) -> Path:
    """A copy of ``database`` without its matches and two-view geometries."""
    out.mkdir(parents=True, exist_ok=True)
    copy = out / "database.db"
    shutil.copy(database, copy)
    with sqlite3.connect(copy) as db:
        db.execute("delete from matches")
        db.execute("delete from two_view_geometries")
    return copy


def main() -> None:
    import pycolmap

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("database", type=Path)
    parser.add_argument("--words", type=int, default=4096)
    parser.add_argument("--per-image", type=int, default=300)
    parser.add_argument("--overlap", type=int, default=5)
    parser.add_argument("--loop-images", type=int, default=5)
    parser.add_argument("--min-index-distance", type=int, default=6)
    parser.add_argument("--out", type=Path, default=Path("/tmp/sfm_vocab_tree"))
    args = parser.parse_args()
    database = cleared_copy(args.database, args.out)
    pycolmap.logging.minloglevel = 2
    began = time.perf_counter()
    rng = np.random.default_rng(0)
    db = pycolmap.Database.open(database)
    chunks = []
    for image in db.read_all_images():
        descriptors = db.read_descriptors(image.image_id).to_float().data
        chunks.append(descriptors[rng.choice(len(descriptors), min(args.per_image, len(descriptors)), replace=False)])
    db.close()
    index = pycolmap.VisualIndex.create(128, 64)
    options = pycolmap.VisualIndex.BuildOptions()
    options.num_visual_words = args.words
    index.build(options, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT,
                                                          np.concatenate(chunks).astype(np.float32)))
    tree = args.out / "tree.bin"
    index.write(tree)
    built = time.perf_counter() - began
    began = time.perf_counter()
    pairing = pycolmap.SequentialPairingOptions(
        overlap=args.overlap, quadratic_overlap=False, loop_detection=True, loop_detection_period=1,
        loop_detection_num_images=args.loop_images, loop_detection_min_index_distance=args.min_index_distance,
        vocab_tree_path=str(tree))
    pycolmap.match_sequential(database, pairing_options=pairing, device=pycolmap.Device.cpu)
    matched = time.perf_counter() - began
    with sqlite3.connect(database) as db:
        pairs = db.execute("select count(*) from matches").fetchone()[0]
    print(f"tree of {index.num_visual_words()} words built in {built:.1f} s; matching {matched:.1f} s, {pairs} pairs")


if __name__ == "__main__":
    main()
