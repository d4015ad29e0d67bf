"""stg_runtime: play Spacetime Gaussian models (numpy + numba + onnxruntime; never torch)."""
from .camera import Camera
from .model import Model, Segment

__version__ = "0.1.0"
