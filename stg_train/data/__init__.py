"""Datasets: cameras and synchronised frames, whatever the layout on disk."""
from .dataset import DataError, Dataset
from .layouts import LAYOUTS, detect_layout, load_dataset
from .n3v import llff_to_camera, load_n3v

__all__ = ["DataError", "Dataset", "LAYOUTS", "detect_layout", "load_dataset", "load_n3v", "llff_to_camera"]
