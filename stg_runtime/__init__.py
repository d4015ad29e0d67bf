"""stg_runtime: play Spacetime Gaussian models (numpy + numba + onnxruntime; never torch).

Public API: `Player` (open a .stg file, render any camera at any time), `Camera`, `Model` / `Segment`
(the in-memory model), `FormatError` (raised for any bad file). The file format and every convention
are specified in formats/stg-v1.md.
"""
from .camera import Camera
from .format import FormatError
from .model import Model, Segment
from .player import Player

__version__ = "0.1.0"
__all__ = ["Camera", "FormatError", "Model", "Player", "Segment"]
