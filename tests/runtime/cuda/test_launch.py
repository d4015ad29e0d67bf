"""stg_runtime.cuda.launch's replay logic, against a stand-in for numba-cuda's dispatcher module (the
real one needs a GPU: tests/runtime/cuda/test_kernels.py's GPU tests run every kernel through it
there).

The stand-in kernel marshals its arguments as numba does (an array: several parameters; a scalar: one,
a ctypes value; a tuple: one per element) into a deterministic parameter list, and records every list
that reaches `launch` (as plain values), so a replay can be compared with what a plain launch of the
same arguments would pass. An np.int8 scalar is marshalled as a non-ctypes value, which cuda.launch
must convert through the kernel's own _prepare_args.
"""
from __future__ import annotations

import ctypes
import gc

import numpy as np
import pytest

from stg_runtime.cuda import launch as cuda_launch


class FakeArray:
    """A device array stand-in: identity matters, and a base address."""

    def __init__(self, address):
        self.address = address


def _marshal(ty, value, out):
    if ty == "array":
        out.extend([0, 0, value.address, 8])
    elif ty == "tuple":
        out.extend(ctypes.c_double(v) for v in value)
    elif isinstance(value, np.int8):
        out.append(("int8", int(value)))
    else:
        out.append(ctypes.c_int64(value) if isinstance(value, int) else ctypes.c_double(value))


def _values(params):
    return [p.value if isinstance(p, ctypes._SimpleCData) else p for p in params]


class FakeCompiled:
    def __init__(self, types):
        self.argument_types = types
        self.conversions = 0

    def _prepare_args(self, ty, value, stream, retr, out):
        self.conversions += 1
        _marshal(ty, value, out)


class FakeKernel:
    """kernel[grid, block](*args) marshals the arguments and calls module.launch, as numba does."""

    def __init__(self, module):
        self.module = module
        self.overloads = {}
        self.plain_launches = 0

    def typeof_pyval(self, value):
        return ("tuple" if isinstance(value, tuple) else "scalar" if isinstance(value, (int, float, np.generic))
                else "array")

    def __getitem__(self, config):
        def call(*args):
            self.plain_launches += 1
            types = tuple(self.typeof_pyval(a) for a in args)
            self.overloads.setdefault(types, FakeCompiled(types))  # (what numba compiles, by argument types)
            params: list = []
            for ty, value in zip(types, args):
                _marshal(ty, value, params)
            self.module.launch("stream", ("config", config), "function", *params)
        return call


class FakeModule:
    _LaunchConfiguration = object

    def __init__(self):
        self.launched = []

    def launch(self, stream, config, function, *params):
        self.launched.append((config, _values(params)))


@pytest.fixture
def fake(monkeypatch):
    module = FakeModule()
    monkeypatch.setitem(cuda_launch._state, "module", module)
    monkeypatch.setattr(cuda_launch, "_prepared", {})
    return module, FakeKernel(module)


def _plain_params(kernel, *args):
    """The parameters a plain launch passes (the stand-in's marshalling, without cuda.launch)."""
    params: list = []
    for a in args:
        _marshal(kernel.typeof_pyval(a), a, params)
    return _values(params)


def test_repeated_launch_is_replayed_with_the_same_parameters(fake):
    module, kernel = fake
    a, b = FakeArray(0x1000), FakeArray(0x2000)
    for _ in range(3):
        cuda_launch.launch(kernel, 4, 256, a, 7, b, (1.0, 2.0))
    assert kernel.plain_launches == 1  # recorded once, replayed twice
    assert len(module.launched) == 3
    want = _plain_params(kernel, a, 7, b, (1.0, 2.0))
    assert all(params == want and config == ("config", (4, 256)) for config, params in module.launched)


def test_changed_scalars_are_converted_again(fake):
    module, kernel = fake
    a = FakeArray(0x1000)
    runs = [(7, (1.0, 2.0), np.int8(1)), (8, (1.0, 2.0), np.int8(1)), (8, (3.0, 4.0), np.int8(1)),
            (8, (3.0, 4.0), np.int8(2)), (7, (1.0, 2.0), np.int8(1))]
    for scalars in runs:
        cuda_launch.launch(kernel, 4, 256, a, *scalars)
    assert kernel.plain_launches == 1
    assert [p for _, p in module.launched] == [_plain_params(kernel, a, *scalars) for scalars in runs]
    # The ctypes-made parameters were converted directly, the np.int8 by the kernel's _prepare_args:
    # 4 arguments when recorded, then twice the np.int8 (runs 4 and 5).
    (compiled,) = kernel.overloads.values()
    assert compiled.conversions == 4 + 2


def test_other_arrays_shapes_or_scalar_types_are_recorded_anew(fake):
    module, kernel = fake
    a, b = FakeArray(0x1000), FakeArray(0x2000)
    cuda_launch.launch(kernel, 4, 256, a, 7)
    cuda_launch.launch(kernel, 4, 256, b, 7)  # another array
    cuda_launch.launch(kernel, 8, 256, a, 7)  # another grid
    cuda_launch.launch(kernel, 4, 256, a, 7.0)  # a float where an int was: numba would pick another overload
    assert kernel.plain_launches == 4
    assert module.launched[1][1] == _plain_params(kernel, b, 7)
    assert module.launched[2][0] == ("config", (8, 256))
    assert module.launched[3][1] == _plain_params(kernel, a, 7.0)


def test_a_dead_array_is_never_mistaken_for_a_new_one_with_its_id(fake):
    """Arrays are recognised by id(); a new array may get a dead one's id (CPython reuses memory), which
    must not replay the dead array's parameters. The reuse is staged: the record is filed under the
    new array's id."""
    module, kernel = fake
    a = FakeArray(0x1000)
    cuda_launch.launch(kernel, 4, 256, a)
    ((key, entry),) = cuda_launch._prepared.items()
    del a
    gc.collect()
    b = FakeArray(0x9000)
    cuda_launch._prepared[key[:3] + (id(b),)] = entry
    cuda_launch.launch(kernel, 4, 256, b)
    assert kernel.plain_launches == 2
    assert module.launched[-1][1] == _plain_params(kernel, b)


def test_unexpected_internals_fall_back_to_plain_launches(fake, monkeypatch):
    module, kernel = fake
    monkeypatch.setattr(FakeCompiled, "_prepare_args", None)  # internals not as expected: not recorded
    a = FakeArray(0x1000)
    for _ in range(2):
        cuda_launch.launch(kernel, 4, 256, a, 7)
    assert kernel.plain_launches == 2 and len(module.launched) == 2 and not cuda_launch._prepared


def test_without_numba_cuda_internals_launches_are_plain(monkeypatch):
    monkeypatch.setitem(cuda_launch._state, "module", None)
    calls = []

    class Plain:
        def __getitem__(self, config):
            return lambda *args: calls.append((config, args))
    cuda_launch.launch(Plain(), 2, 32, np.zeros(3), 5)
    assert calls and calls[0][0] == (2, 32) and calls[0][1][1] == 5
