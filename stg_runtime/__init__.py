"""stg_runtime: play Spacetime Gaussian models (numpy + numba + onnxruntime; never torch).

Public API: `Player` (open a .stg file, render any camera at any time), `Camera`, `Model` / `Segment`
(the in-memory model), `FormatError` (raised for any bad file), `RenderError` (raised when rendering a
loaded model fails), `Limits` (what a file may declare). The file format and every convention
are specified in formats/stg-v1.md.

Importing it sets ORT_DISABLE_TELEMETRY=1 unless the environment already sets it: onnxruntime (1.29 and
later) otherwise keeps a usage database under ~/.cache/Microsoft and sends telemetry over the network,
and it reads the variable only when it is first imported (docs/security.md).
"""
import os
import sys
import warnings

if "onnxruntime" in sys.modules and "ORT_DISABLE_TELEMETRY" not in os.environ:
    warnings.warn("stg_runtime was imported after onnxruntime, so ORT_DISABLE_TELEMETRY=1 cannot take effect: "
                  "onnxruntime may send telemetry. Import stg_runtime first, or set ORT_DISABLE_TELEMETRY=1 in "
                  "the environment.", RuntimeWarning, stacklevel=2)
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

from .camera import Camera  # noqa: E402
from .format import FormatError, Limits  # noqa: E402
from .model import Model, Segment  # noqa: E402
from .player import Player, RenderError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["Camera", "FormatError", "Limits", "Model", "Player", "RenderError", "Segment"]
