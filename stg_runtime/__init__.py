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

__version__ = "0.1.0"
__all__ = ["Camera", "FormatError", "Limits", "Model", "Player", "RenderError", "Segment"]

#: Public name -> its module. Imported on first use (PEP 562), so that a command line's `--help` and
#: argument errors, which import only stg_runtime's light modules, do not wait for numba.
_HOMES = {"Camera": "camera", "FormatError": "format", "Limits": "format", "Model": "model", "Segment": "model",
          "Player": "player", "RenderError": "player"}


def __getattr__(name: str):
    if name in _HOMES:
        import importlib

        return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_HOMES))
