"""Datasets: cameras and synchronised frames, whatever the layout on disk."""
from .dataset import DataError, Dataset
from .n3v import llff_to_camera, load_n3v

__all__ = ["DataError", "Dataset", "load_n3v", "llff_to_camera"]
