"""A minimal ONNX codec for the colour decoder, without the `onnx` package (standard library + numpy).

Writes a bias-free MLP as an ONNX ModelProto, reads the protobuf wire format back (bounds-checked,
no recursion), checks that a graph is safe to hand to onnxruntime (no external data) and recovers
an MLP's weights from a graph. Field numbers are those of onnx/onnx.proto.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VARINT, I64, LEN, I32 = 0, 1, 2, 5  # protobuf wire types
FLOAT, EXTERNAL = 1, 1  # TensorProto.DataType.FLOAT, TensorProto.DataLocation.EXTERNAL
MAX_DEPTH = 64  # nesting of graphs inside attributes that check_graph follows before refusing

# -- writing -------------------------------------------------------------------------------------


def _varint(value: int) -> bytes:
    value &= (1 << 64) - 1  # negative int64 as two's complement
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _int(field: int, value: int) -> bytes:
    return _varint(field << 3 | VARINT) + _varint(value)


def _len(field: int, payload: bytes | str) -> bytes:
    payload = payload.encode() if isinstance(payload, str) else payload
    return _varint(field << 3 | LEN) + _varint(len(payload)) + payload


def _value_info(name: str, width: int) -> bytes:
    """ValueInfoProto: float32 tensor of shape ("P", width)."""
    shape = _len(1, _len(2, "P")) + _len(1, _int(1, width))
    tensor_type = _int(1, FLOAT) + _len(2, shape)
    return _len(1, name) + _len(2, _len(1, tensor_type))


def mlp_to_onnx(weights: list[np.ndarray]) -> bytes:
    """An ONNX model computing y = W_n(...relu(W_1 x)) for x (P, in_0) float32 -> y (P, out_n).

    weights[k]: (out_k, in_k), like torch Linear weights. Nodes: MatMul(x, W_k^T), Relu between layers.
    """
    weights = [np.asarray(w, dtype=np.float32) for w in weights]
    if not weights or any(w.ndim != 2 for w in weights):
        raise ValueError("mlp_to_onnx: need a non-empty list of 2-D (out, in) weight matrices")
    for k in range(1, len(weights)):
        if weights[k].shape[1] != weights[k - 1].shape[0]:
            raise ValueError(f"mlp_to_onnx: layer {k} takes {weights[k].shape[1]} inputs, "
                             f"layer {k - 1} gives {weights[k - 1].shape[0]}")
    nodes, inits, cur = [], [], "x"
    for k, w in enumerate(weights):
        name, out = f"W{k}", ("y" if k == len(weights) - 1 else f"h{k}")
        inits.append(_int(1, w.shape[1]) + _int(1, w.shape[0]) + _int(2, FLOAT) + _len(8, name)
                     + _len(9, np.ascontiguousarray(w.T, dtype="<f4").tobytes()))
        nodes.append(_len(1, cur) + _len(1, name) + _len(2, out) + _len(3, f"matmul{k}") + _len(4, "MatMul"))
        cur = out
        if out != "y":
            cur = f"a{k}"
            nodes.append(_len(1, out) + _len(2, cur) + _len(3, f"relu{k}") + _len(4, "Relu"))
    graph = b"".join(_len(1, n) for n in nodes) + _len(2, "stg_decoder") + b"".join(_len(5, t) for t in inits)
    graph += _len(11, _value_info("x", weights[0].shape[1])) + _len(12, _value_info("y", weights[-1].shape[0]))
    return _int(1, 8) + _len(2, "stg_runtime") + _len(7, graph) + _len(8, _int(2, 17))


# -- reading -------------------------------------------------------------------------------------


def _read_varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("protobuf: truncated varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise ValueError("protobuf: varint longer than 10 bytes")


def parse(data) -> dict[int, list]:
    """The fields of one protobuf message: field number -> values in wire order.

    Varints are ints (unsigned; see _signed), 64- and 32-bit fields are 8 / 4 raw bytes, length-delimited
    fields are memoryviews into `data` (sub-messages are parsed by calling parse again). Raises
    ValueError on malformed input.
    """
    buf = memoryview(data).cast("B")
    fields: dict[int, list] = {}
    pos = 0
    while pos < len(buf):
        key, pos = _read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise ValueError("protobuf: field number 0")
        if wire == VARINT:
            value, pos = _read_varint(buf, pos)
        elif wire in (I64, I32, LEN):
            if wire == LEN:
                size, pos = _read_varint(buf, pos)
            else:
                size = 8 if wire == I64 else 4
            if pos + size > len(buf):
                raise ValueError(f"protobuf: field {number} runs past the end of the message")
            value = buf[pos:pos + size] if wire == LEN else bytes(buf[pos:pos + size])
            pos += size
        else:
            raise ValueError(f"protobuf: unsupported wire type {wire} (field {number})")
        fields.setdefault(number, []).append(value)
    return fields


def _signed(v: int) -> int:
    """A varint as int64 (two's complement; bits above 64 are dropped, as protobuf does)."""
    v &= (1 << 64) - 1
    return v - (1 << 64) if v >= 1 << 63 else v


def _messages(fields: dict, number: int) -> list[memoryview]:
    values = fields.get(number, [])
    if not all(isinstance(v, memoryview) for v in values):
        raise ValueError(f"protobuf: field {number} should be length-delimited")
    return values


def _strings(fields: dict, number: int) -> list[str]:
    return [bytes(v).decode("utf-8") for v in _messages(fields, number)]


def _scalar(fields: dict, number: int, default):
    """The last value of a singular field (protobuf semantics), checked to be of default's type."""
    value = fields.get(number, [default])[-1]
    if not isinstance(value, type(default)):
        raise ValueError(f"protobuf: field {number} has the wrong wire type")
    return value


def _ints(fields: dict, number: int) -> list[int]:
    """A repeated int64 field, packed or not."""
    out = []
    for v in fields.get(number, []):
        if isinstance(v, int):
            out.append(_signed(v))
        elif isinstance(v, memoryview):
            pos = 0
            while pos < len(v):
                value, pos = _read_varint(v, pos)
                out.append(_signed(value))
        else:
            raise ValueError(f"protobuf: field {number} should be an integer")
    return out


@dataclass
class Node:
    op_type: str
    inputs: list[str]
    outputs: list[str]
    domain: str
    attributes: dict  # name -> int or float (INT / FLOAT attributes), None for other kinds


@dataclass
class Graph:
    nodes: list[Node]
    initializers: dict  # name -> float32 array of its dims, or None when not float32 data in the file
    inputs: list[str]  # graph inputs that are not initializers
    outputs: list[str]


def _tensor(fields: dict) -> np.ndarray | None:
    """TensorProto -> float32 array (from raw_data or float_data), None for other types or external data."""
    if _scalar(fields, 2, 0) != FLOAT or _scalar(fields, 14, 0) == EXTERNAL or 13 in fields:
        return None
    dims = _ints(fields, 1)
    if 9 in fields:
        raw = bytes(_scalar(fields, 9, memoryview(b"")))
    elif all(isinstance(v, (bytes, memoryview)) for v in fields.get(4, [])):  # packed, or fixed32 each
        raw = b"".join(bytes(v) for v in fields.get(4, []))
    else:
        raise ValueError("onnx: float_data should be packed or 32-bit values")
    if any(d < 0 for d in dims) or len(raw) != 4 * math.prod(dims):
        raise ValueError("onnx: tensor data does not match its dims")
    return np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(dims)


def _attribute(fields: dict):
    kind = _scalar(fields, 20, 0)
    if kind == 2 or (kind == 0 and 3 in fields):
        return _signed(_scalar(fields, 3, 0))
    if kind == 1 or (kind == 0 and 2 in fields):
        return float(np.frombuffer(_scalar(fields, 2, b"\0\0\0\0"), dtype="<f4")[0])
    return None


def _text(fields: dict, number: int) -> str:
    return bytes(_scalar(fields, number, memoryview(b""))).decode("utf-8")


def read_graph(data: bytes) -> Graph:
    """The main graph of an ONNX ModelProto: nodes in order, initializers, inputs and outputs."""
    graphs = _messages(parse(data), 7)
    if not graphs:
        raise ValueError("onnx: the model has no graph")
    g = parse(b"".join(bytes(v) for v in graphs))  # repeated occurrences of a message field merge
    nodes = []
    for raw in _messages(g, 1):
        n = parse(raw)
        attributes = {_text(a, 1): _attribute(a) for a in map(parse, _messages(n, 5))}
        nodes.append(Node(_text(n, 4), _strings(n, 1), _strings(n, 2), _text(n, 7), attributes))
    inits = {_text(t, 8): _tensor(t) for t in map(parse, _messages(g, 5))}
    inputs = [_text(parse(v), 1) for v in _messages(g, 11)]
    outputs = [_text(parse(v), 1) for v in _messages(g, 12)]
    return Graph(nodes, inits, [name for name in inputs if name not in inits], outputs)


# message -> {field number: message type} for every field through which a TensorProto can be reached
_CHILDREN = {
    "model": {7: "graph", 20: "training", 25: "function"},
    "training": {1: "graph", 2: "graph"},
    "function": {7: "node", 11: "attribute"},
    "graph": {1: "node", 5: "tensor", 15: "sparse"},
    "node": {5: "attribute"},
    "attribute": {5: "tensor", 6: "graph", 10: "tensor", 11: "graph", 22: "sparse", 23: "sparse"},
    "sparse": {1: "tensor", 2: "tensor"},
    "tensor": {},
}


def check_graph(data: bytes) -> None:
    """Raise ValueError unless `data` is a parseable ONNX model with a graph of exactly one input and one
    output in which no tensor (initializers, constants, nested graphs, functions) uses external data."""
    graph = read_graph(data)
    stack = [("model", memoryview(data), 0)]
    while stack:
        kind, raw, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise ValueError(f"onnx: messages nested more than {MAX_DEPTH} deep")
        fields = parse(raw)
        if kind == "tensor" and (_scalar(fields, 14, 0) == EXTERNAL or 13 in fields):
            raise ValueError(f"onnx: tensor {_text(fields, 8)!r} refers to external data")
        for number, child in _CHILDREN[kind].items():
            stack.extend((child, v, depth + 1) for v in _messages(fields, number))
    if len(graph.inputs) != 1 or len(graph.outputs) != 1:
        raise ValueError(f"onnx: the graph must have one input and one output, "
                         f"has {len(graph.inputs)} and {len(graph.outputs)}")


def _linear(node: Node, x: str, inits: dict) -> np.ndarray | None:
    """The (out, in) weight of a bias-free MatMul(x, W) or Gemm(x, W) node, or None."""
    w = inits.get(node.inputs[1]) if len(node.inputs) >= 2 and node.inputs[0] == x else None
    if w is None or w.ndim != 2:
        return None
    if node.op_type == "MatMul" and len(node.inputs) == 2 and not node.attributes:
        return np.ascontiguousarray(w.T)
    if node.op_type == "Gemm" and node.inputs[2:] in ([], [""]):  # no bias C
        attrs = {"alpha": 1.0, "beta": 1.0, "transA": 0, "transB": 0, **node.attributes}
        if attrs == {"alpha": 1.0, "beta": 1.0, "transA": 0, "transB": attrs["transB"]} and attrs["transB"] in (0, 1):
            return w.copy() if attrs["transB"] else np.ascontiguousarray(w.T)
    return None


def mlp_weights(data: bytes) -> list[np.ndarray] | None:
    """The (out, in) float32 weights if the graph is exactly MatMul/Gemm(x, W) [Relu MatMul/Gemm]*, else None.

    Gemm is accepted without bias, with alpha = beta = 1, transA = 0. Raises ValueError for bytes that
    are not a parseable ONNX model."""
    graph = read_graph(data)
    if len(graph.inputs) != 1 or len(graph.outputs) != 1:
        return None
    weights, cur = [], graph.inputs[0]
    for k, node in enumerate(graph.nodes):
        if node.domain not in ("", "ai.onnx") or len(node.outputs) != 1:
            return None
        if k % 2 == 0:
            w = _linear(node, cur, graph.initializers)
            if w is None or (weights and w.shape[1] != weights[-1].shape[0]):
                return None
            weights.append(w)
        elif node.op_type != "Relu" or node.inputs != [cur] or node.attributes:
            return None
        cur = node.outputs[0]
    if len(graph.nodes) % 2 == 0 or cur != graph.outputs[0]:
        return None
    return weights
