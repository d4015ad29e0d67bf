"""Kernel launches that skip numba's per-call work when they repeat.

    launch(kernel, griddim, blockdim, *args)      same as kernel[griddim, blockdim](*args)

A plain numba launch types every argument, picks the compiled overload and converts each array into its
kernel parameters, in Python, which can take longer than the kernel runs (docs/performance.md has the measured
costs). `launch` does that work once per kernel, launch shape and set of arrays (recognised by
identity, so callers keep their buffers from frame to frame) and scalar types, records the parameters
numba passes to cuda.core's launch, and afterwards replays that launch directly. Scalar arguments are
converted again only when their values change: with the ctypes types numba gave their parameters when
these reproduce numba's conversion, else by numba (a tuple argument must keep its element types).

This relies on numba-cuda's internals (cuda.core launches, the compiled kernel's `_prepare_args`), and
recording swaps numba-cuda's launch function for a moment (record from one thread at a time). Where
the internals differ (another numba-cuda version, numba's built-in CUDA target, the simulator), or
when an argument cannot be recorded, `launch` is the plain numba launch.
"""
from __future__ import annotations

import ctypes
import weakref

import numpy as np
from numba import config as _numba_config

_SCALARS = (bool, int, float, tuple, np.generic)
#: Most prepared launches kept; beyond that the table starts again (entries hold only weak references).
MAX_PREPARED = 512

_prepared: dict = {}
_state: dict = {}  # "module": numba-cuda's dispatcher module, once checked; None: plain launches only


class _Prepared:
    """A recorded launch: cuda.core's stream, config and kernel, the parameters, and per scalar
    argument its place in them (to convert it again when it changes)."""

    __slots__ = ("stream", "config", "function", "params", "scalars", "compiled", "arrays")

    # scalars: (argument index, start, stop, value, converters): the argument's parameters are
    # params[start:stop]; converters, when not None, turn its value (a tuple's elements) into them.

    def __init__(self, stream, config, function, params, scalars, compiled, arrays):
        self.stream, self.config, self.function, self.params = stream, config, function, params
        self.scalars, self.compiled, self.arrays = scalars, compiled, arrays


def _dispatcher_module():
    """numba-cuda's dispatcher module if it launches through cuda.core as this module expects, else None."""
    if "module" not in _state:
        module = None
        if not _numba_config.ENABLE_CUDASIM:
            try:
                from numba.cuda import dispatcher as module
                if not (callable(getattr(module, "launch", None)) and hasattr(module, "_LaunchConfiguration")):
                    module = None
            except ImportError:
                module = None
        _state["module"] = module
    return _state["module"]


def launch(kernel, griddim, blockdim, *args) -> None:
    """kernel[griddim, blockdim](*args), replayed from a recording when it repeats (see the module)."""
    module = _dispatcher_module()
    if module is None:
        kernel[griddim, blockdim](*args)
        return
    key = (id(kernel), griddim, blockdim) + tuple(type(a) if isinstance(a, _SCALARS) else id(a) for a in args)
    entry = _prepared.get(key)
    if entry is not None and all(ref() is args[i] for i, ref in entry.arrays):
        params = entry.params
        for i, _, _, value, _ in entry.scalars:
            if args[i] != value:
                params = _rebuild(entry, params, args)
                break
        module.launch(entry.stream, entry.config, entry.function, *params)
        return
    entry = _record(module, kernel, griddim, blockdim, args)
    if entry is not None:
        if len(_prepared) >= MAX_PREPARED:
            _prepared.clear()
        _prepared[key] = entry


def _rebuild(entry: _Prepared, params, args):
    """The parameters with changed scalar arguments converted again; recorded in the entry."""
    params = list(params)
    scalars = []
    for i, start, stop, value, converters in entry.scalars:
        if args[i] != value:
            value = args[i]
            if converters is not None:
                new = [convert(v) for convert, v in zip(converters, value if isinstance(value, tuple) else (value,))]
            else:
                new = []
                entry.compiled._prepare_args(entry.compiled.argument_types[i], value, entry.stream, [], new)
            if len(new) != stop - start:
                raise RuntimeError("cuda.launch: a scalar argument changed its parameter count")
            params[start:stop] = new
        scalars.append((i, start, stop, value, converters))
    entry.params, entry.scalars = params, scalars
    return params


def _record(module, kernel, griddim, blockdim, args):
    """Launch the plain way while recording what numba hands to cuda.core; a _Prepared, or None when
    the launch cannot be replayed (then it was still launched once, the plain way)."""
    captured = []
    plain = module.launch

    def capture(stream, config, function, *params):
        captured.append((stream, config, function, params))
        return plain(stream, config, function, *params)

    module.launch = capture
    try:
        kernel[griddim, blockdim](*args)
    finally:
        module.launch = plain
    if len(captured) != 1:
        return None
    stream, config, function, params = captured[0]
    try:
        compiled = kernel.overloads[tuple(kernel.typeof_pyval(a) for a in args)]
        scalars, arrays, start = [], [], 0
        for i, (ty, value) in enumerate(zip(compiled.argument_types, args)):
            part: list = []
            compiled._prepare_args(ty, value, stream, [], part)
            if isinstance(value, _SCALARS):
                scalars.append((i, start, start + len(part), value, _converters(value, part)))
            else:
                arrays.append((i, weakref.ref(value)))
            start += len(part)
        if start != len(params):
            return None
    except (AttributeError, KeyError, TypeError):  # internals not as expected, or no weak reference
        return None
    return _Prepared(stream, config, function, list(params), scalars, compiled, arrays)


def _plain(p):
    return p.value if isinstance(p, ctypes._SimpleCData) else p


def _converters(value, part):
    """Per parameter of a scalar argument (a tuple: one per element), the type that made it (a ctypes
    type, or bool/int/float), when calling those on the value's elements gives numba's parameters
    again (numba's own conversion, a few microseconds per element, is then skipped); else None."""
    flat = value if isinstance(value, tuple) else (value,)
    converters = tuple(type(p) for p in part)
    if len(flat) != len(part) or not all(issubclass(c, (ctypes._SimpleCData, bool, int, float)) for c in converters):
        return None
    try:
        if all(_plain(c(v)) == _plain(p) for c, v, p in zip(converters, flat, part)):
            return converters
    except (TypeError, ValueError):
        pass
    return None
