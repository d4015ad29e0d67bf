"""`stg-prep`: from a folder of raw videos (one per camera) to the rig layout that `stg-train` reads.

    inputs.py     finding the cameras' clips and checking them against each other
    sync.py       integer frame offsets from the pictures
    calibrate.py  intrinsics and poses with pycolmap
    write.py      the rig folder: images/<camera>/<frame>.png, sparse/0, prep.json
    pipeline.py   prepare(videos, out, ...), the entry point, and prepared (reuse)

Importing this package imports numpy only; OpenCV and pycolmap load when they are needed.
"""
from .inputs import PrepError
from .pipeline import prepare, prepared

__all__ = ["PrepError", "prepare", "prepared"]
