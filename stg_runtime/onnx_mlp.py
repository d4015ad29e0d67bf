"""The colour decoder's ONNX graphs, without the `onnx` package (standard library + numpy).

A decoder is valid only as a member of the MLP family of formats/stg-v1.md (section 2, "The decoder
graph"): layers of MatMul or Gemm (optionally with a bias, or followed by Add of a bias), Relu between
layers, bounded widths, finite float32 weights, and nothing else. Safety comes by construction:

    read_mlp(data) -> MLP        parses a graph into that description, or raises ValueError
    MLP.to_onnx() -> bytes       the one graph a reader ever gives onnxruntime, re-serialised from the
                                 description (never the file's bytes)
    canonical(data) -> bytes     read_mlp(data).to_onnx()
    mlp_to_onnx(weights, biases) the writer (trainer, importers)

The protobuf reader is bounded and iterative: field keys must fit 32 bits and varints 64 (as protobuf
and onnxruntime read them), every message may hold only the fields listed here, with their wire types.
Field numbers are those of onnx/onnx.proto.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VARINT, I64, LEN, I32 = 0, 1, 2, 5  # protobuf wire types
FLOAT = 1  # TensorProto.DataType.FLOAT
#: Bounds of a valid decoder (formats/stg-v1.md): layers, and the width of every layer's input and output.
MAX_LAYERS = 8
MAX_WIDTH = 256
#: The ONNX opset and IR version of the graphs this module writes.
OPSET, IR_VERSION = 17, 8

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


def _initializer(name: str, array: np.ndarray) -> bytes:
    dims = b"".join(_int(1, d) for d in array.shape)
    return dims + _int(2, FLOAT) + _len(8, name) + _len(9, np.ascontiguousarray(array, dtype="<f4").tobytes())


def mlp_to_onnx(weights: list[np.ndarray], biases: list[np.ndarray | None] | None = None) -> bytes:
    """An ONNX model computing y = L_n(...relu(L_1 x)) for x (P, in_0) float32 -> y (P, out_n), with
    L_k(h) = h W_k^T (+ b_k).

    weights[k]: (out_k, in_k), like torch Linear weights; biases[k]: (out_k,) or None (default: none).
    Nodes: MatMul(h, W_k^T), Add(., b_k) where there is a bias, Relu between layers."""
    weights = [np.asarray(w, dtype=np.float32) for w in weights]
    biases = [None] * len(weights) if biases is None else [None if b is None else np.asarray(b, np.float32)
                                                          for b in biases]
    if not weights or any(w.ndim != 2 for w in weights) or len(biases) != len(weights):
        raise ValueError("mlp_to_onnx: need a non-empty list of 2-D (out, in) weight matrices and one bias "
                         "(or None) per layer")
    for k in range(len(weights)):
        if k and weights[k].shape[1] != weights[k - 1].shape[0]:
            raise ValueError(f"mlp_to_onnx: layer {k} takes {weights[k].shape[1]} inputs, "
                             f"layer {k - 1} gives {weights[k - 1].shape[0]}")
        if biases[k] is not None and biases[k].shape != (weights[k].shape[0],):
            raise ValueError(f"mlp_to_onnx: bias {k} has shape {biases[k].shape}, expected ({weights[k].shape[0]},)")
    nodes, inits, cur = [], [], "x"
    for k, (w, b) in enumerate(zip(weights, biases)):
        last = k == len(weights) - 1
        out = "y" if last and b is None else f"h{k}"
        inits.append(_initializer(f"W{k}", w.T))
        nodes.append(_len(1, cur) + _len(1, f"W{k}") + _len(2, out) + _len(3, f"matmul{k}") + _len(4, "MatMul"))
        cur = out
        if b is not None:
            out = "y" if last else f"b{k}"
            inits.append(_initializer(f"B{k}", b))
            nodes.append(_len(1, cur) + _len(1, f"B{k}") + _len(2, out) + _len(3, f"add{k}") + _len(4, "Add"))
            cur = out
        if not last:
            nodes.append(_len(1, cur) + _len(2, f"a{k}") + _len(3, f"relu{k}") + _len(4, "Relu"))
            cur = f"a{k}"
    graph = b"".join(_len(1, n) for n in nodes) + _len(2, "stg_decoder") + b"".join(_len(5, t) for t in inits)
    graph += _len(11, _value_info("x", weights[0].shape[1])) + _len(12, _value_info("y", weights[-1].shape[0]))
    return _int(1, IR_VERSION) + _len(2, "stg_runtime") + _len(7, graph) + _len(8, _int(2, OPSET))


# -- the protobuf wire format --------------------------------------------------------------------


def _read_varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("protobuf: truncated varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            if result >> 64:
                raise ValueError("protobuf: varint beyond 64 bits")
            return result, pos
        shift += 7
        if shift >= 70:
            raise ValueError("protobuf: varint longer than 10 bytes")


def parse(data) -> dict[int, list]:
    """The fields of one protobuf message: field number -> values in wire order.

    Varints are ints (unsigned; see _signed), 64- and 32-bit fields are 8 / 4 raw bytes, length-delimited
    fields are memoryviews into `data` (sub-messages are parsed by calling parse again). Raises
    ValueError on malformed input, including keys beyond 32 bits (which protobuf and onnxruntime read
    modulo 2^32: such a key must not mean one field to this reader and another to them).
    """
    buf = memoryview(data).cast("B")
    fields: dict[int, list] = {}
    pos = 0
    while pos < len(buf):
        key, pos = _read_varint(buf, pos)
        if key >> 32:
            raise ValueError("protobuf: field key beyond 32 bits")
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
    """A varint as int64 (two's complement)."""
    return v - (1 << 64) if v >= 1 << 63 else v


#: Per message type of a decoder, the fields it may hold: field number -> (wire type, meaning).
_FIELDS = {
    "model": {1: (VARINT, "ir_version"), 2: (LEN, "producer_name"), 3: (LEN, "producer_version"),
              4: (LEN, "domain"), 5: (VARINT, "model_version"), 6: (LEN, "doc_string"), 7: (LEN, "graph"),
              8: (LEN, "opset_import"), 14: (LEN, "metadata_props")},
    "opset": {1: (LEN, "domain"), 2: (VARINT, "version")},
    "graph": {1: (LEN, "node"), 2: (LEN, "name"), 5: (LEN, "initializer"), 10: (LEN, "doc_string"),
              11: (LEN, "input"), 12: (LEN, "output"), 13: (LEN, "value_info")},
    "node": {1: (LEN, "input"), 2: (LEN, "output"), 3: (LEN, "name"), 4: (LEN, "op_type"),
             5: (LEN, "attribute"), 6: (LEN, "doc_string"), 7: (LEN, "domain")},
    "attribute": {1: (LEN, "name"), 2: (I32, "f"), 3: (VARINT, "i"), 13: (LEN, "doc_string"), 20: (VARINT, "type")},
    "tensor": {1: (VARINT, "dims"), 2: (VARINT, "data_type"), 4: (LEN, "float_data"), 8: (LEN, "name"),
               9: (LEN, "raw_data"), 12: (LEN, "doc_string"), 14: (VARINT, "data_location")},
    "value_info": {1: (LEN, "name"), 2: (LEN, "type"), 3: (LEN, "doc_string")},
}
#: Fields that exist in ONNX but never in a decoder, with what they would bring (for the messages).
_FORBIDDEN = {("tensor", 13): "refers to external data", ("graph", 15): "has sparse initializers",
              ("model", 20): "has training information", ("model", 25): "has local functions",
              ("attribute", 5): "holds a tensor", ("attribute", 6): "holds a subgraph",
              ("attribute", 11): "holds subgraphs", ("node", 8): "names an overload"}
_SINGULAR = {"graph", "name", "op_type", "domain", "data_type", "raw_data", "data_location", "f", "i", "type",
             "ir_version", "version"}


def _message(raw, kind: str) -> dict[str, list]:
    """A message of type `kind` parsed and checked against _FIELDS: field name -> values."""
    fields = parse(raw)
    out: dict[str, list] = {}
    for number, values in fields.items():
        if number not in _FIELDS[kind]:
            why = _FORBIDDEN.get((kind, number), "is not allowed in a decoder")
            raise ValueError(f"onnx: {kind} field {number} {why}")
        wire, name = _FIELDS[kind][number]
        want = memoryview if wire == LEN else (int if wire == VARINT else bytes)
        if name == "float_data" or name == "dims":  # packed (LEN) or one value per entry
            want = (memoryview, bytes) if name == "float_data" else (int, memoryview)
        if not all(isinstance(v, want) for v in values) or (wire == I32 and any(
                isinstance(v, bytes) and len(v) != 4 for v in values)):
            raise ValueError(f"onnx: {kind} field {name} has the wrong wire type")
        if name in _SINGULAR and len(values) > 1:
            raise ValueError(f"onnx: {kind} field {name} is repeated")
        out[name] = values
    return out


def _text(fields: dict, name: str) -> str:
    values = fields.get(name)
    return bytes(values[-1]).decode("utf-8") if values else ""


def _ints(values) -> list[int]:
    """A repeated int64 field, packed or not."""
    out = []
    for v in values:
        if isinstance(v, int):
            out.append(_signed(v))
            continue
        pos = 0
        while pos < len(v):
            value, pos = _read_varint(v, pos)
            out.append(_signed(value))
    return out


def _tensor(raw) -> tuple[str, np.ndarray]:
    """An initializer: (name, float32 array of 1 or 2 dims, finite, at most MAX_WIDTH^2 values)."""
    t = _message(raw, "tensor")
    name = _text(t, "name")
    if t.get("data_type", [0])[0] != FLOAT:
        raise ValueError(f"onnx: initializer {name!r} is not float32")
    if t.get("data_location", [0])[0] != 0:
        raise ValueError(f"onnx: initializer {name!r} refers to external data")
    dims = _ints(t.get("dims", []))
    if not 1 <= len(dims) <= 2 or any(d < 1 or d > MAX_WIDTH for d in dims):
        raise ValueError(f"onnx: initializer {name!r} has dims {dims}; a decoder's weights are 1-D or 2-D, "
                         f"each dimension 1..{MAX_WIDTH}")
    if "raw_data" in t and "float_data" in t:
        raise ValueError(f"onnx: initializer {name!r} has both raw_data and float_data")
    raw_data = bytes(t["raw_data"][0]) if "raw_data" in t else b"".join(bytes(v) for v in t.get("float_data", []))
    if len(raw_data) != 4 * math.prod(dims):
        raise ValueError(f"onnx: initializer {name!r} holds {len(raw_data)} bytes, its dims {dims} need "
                         f"{4 * math.prod(dims)}")
    array = np.frombuffer(raw_data, dtype="<f4").astype(np.float32).reshape(dims)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"onnx: initializer {name!r} has non-finite values")
    return name, array


@dataclass(frozen=True, eq=False)
class MLP:
    """A decoder as formats/stg-v1.md describes it: weights[k] (out_k, in_k) float32, biases[k] (out_k,)
    float32 or None; Relu between layers, none after the last."""

    weights: tuple
    biases: tuple

    @property
    def input_width(self) -> int:
        return int(self.weights[0].shape[1])

    @property
    def output_width(self) -> int:
        return int(self.weights[-1].shape[0])

    def to_onnx(self) -> bytes:
        """The canonical graph of this MLP (mlp_to_onnx)."""
        return mlp_to_onnx(list(self.weights), list(self.biases))


def _attributes(node: dict) -> dict:
    """A node's attributes: name -> int or float (the only kinds a decoder's Gemm uses)."""
    out = {}
    for raw in node.get("attribute", []):
        a = _message(raw, "attribute")
        name = _text(a, "name")
        if name in out:
            raise ValueError(f"onnx: attribute {name!r} is repeated")
        if ("f" in a) == ("i" in a):
            raise ValueError(f"onnx: attribute {name!r} must hold one number")
        out[name] = float(np.frombuffer(a["f"][0], "<f4")[0]) if "f" in a else _signed(a["i"][0])
    return out


def _linear(node: dict, op: str, inputs: list, attrs: dict, inits: dict, used: set):
    """(weight (out, in), bias or None) of a MatMul or Gemm node's initializers."""
    def take(name):
        if name not in inits or name in used:
            raise ValueError(f"onnx: {op} input {name!r} is not an unused initializer")
        used.add(name)
        return inits[name]

    if op == "MatMul":
        if len(inputs) != 2 or attrs:
            raise ValueError("onnx: MatMul takes two inputs and no attributes")
        w = take(inputs[1])
        if w.ndim != 2:
            raise ValueError("onnx: a MatMul weight must be 2-D")
        return np.ascontiguousarray(w.T), None
    settings = {"alpha": 1.0, "beta": 1.0, "transA": 0, "transB": 0, **attrs}
    if set(settings) != {"alpha", "beta", "transA", "transB"} or settings["alpha"] != 1.0 \
            or settings["beta"] != 1.0 or settings["transA"] != 0 or settings["transB"] not in (0, 1):
        raise ValueError(f"onnx: Gemm attributes {attrs} (a decoder's Gemm has alpha = beta = 1, transA = 0)")
    if len(inputs) not in (2, 3):
        raise ValueError("onnx: Gemm takes two or three inputs")
    w = take(inputs[1])
    if w.ndim != 2:
        raise ValueError("onnx: a Gemm weight must be 2-D")
    w = w.copy() if settings["transB"] else np.ascontiguousarray(w.T)
    bias = None
    if len(inputs) == 3 and inputs[2] != "":
        bias = _bias(take(inputs[2]), w.shape[0])
    return w, bias


def _bias(array: np.ndarray, width: int) -> np.ndarray:
    """A bias of shape (width,) or (1, width) as (width,); ValueError for any other shape."""
    if array.shape not in ((width,), (1, width)):
        raise ValueError(f"onnx: a bias of shape {list(array.shape)} for a layer of {width} outputs")
    return array.reshape(width)


def read_mlp(data) -> MLP:
    """The decoder graph `data` (ONNX ModelProto bytes) as an MLP; ValueError saying why when it is not a
    valid decoder (formats/stg-v1.md, section 2: the MLP family, its bounds, finite weights, no other
    fields, ops, inputs or initializers)."""
    model = _message(data, "model")
    for raw in model.get("opset_import", []):
        _message(raw, "opset")
    if "graph" not in model:
        raise ValueError("onnx: the model has no graph")
    graph = _message(model["graph"][0], "graph")
    inits: dict[str, np.ndarray] = {}
    for raw in graph.get("initializer", []):
        name, array = _tensor(raw)
        if name in inits:
            raise ValueError(f"onnx: initializer {name!r} is repeated")
        inits[name] = array
    inputs = [_text(_message(v, "value_info"), "name") for v in graph.get("input", [])]
    inputs = [name for name in inputs if name not in inits]
    outputs = [_text(_message(v, "value_info"), "name") for v in graph.get("output", [])]
    for v in graph.get("value_info", []):
        _message(v, "value_info")
    if len(inputs) != 1 or len(outputs) != 1:
        raise ValueError(f"onnx: the graph must have one input and one output, has {len(inputs)} and {len(outputs)}")
    weights, biases, used, cur, expect = [], [], set(), inputs[0], "linear"
    for raw in graph.get("node", []):
        node = _message(raw, "node")
        op, domain = _text(node, "op_type"), _text(node, "domain")
        node_inputs = [bytes(v).decode("utf-8") for v in node.get("input", [])]
        node_outputs = [bytes(v).decode("utf-8") for v in node.get("output", [])]
        attrs = _attributes(node)
        if domain not in ("", "ai.onnx"):
            raise ValueError(f"onnx: node {op!r} of domain {domain!r} (a decoder uses the standard ops only)")
        if len(node_outputs) != 1 or not node_outputs[0] or node_outputs[0] in inits or node_outputs[0] == inputs[0]:
            raise ValueError(f"onnx: node {op!r} must have one new output")
        if op in ("MatMul", "Gemm") and expect == "linear":
            if node_inputs[:1] != [cur]:
                raise ValueError(f"onnx: {op} does not take the previous layer's output")
            w, b = _linear(node, op, node_inputs, attrs, inits, used)
            weights.append(w)
            biases.append(b)
            expect = "after linear"
        elif op == "Add" and expect == "after linear" and biases[-1] is None and not attrs:
            if len(node_inputs) != 2 or cur not in node_inputs:
                raise ValueError("onnx: Add must add a bias to the previous layer's output")
            name = node_inputs[1] if node_inputs[0] == cur else node_inputs[0]
            if name not in inits or name in used:
                raise ValueError(f"onnx: Add input {name!r} is not an unused initializer")
            used.add(name)
            biases[-1] = _bias(inits[name], weights[-1].shape[0])
            expect = "after add"
        elif op == "Relu" and expect in ("after linear", "after add") and not attrs:
            if node_inputs != [cur]:
                raise ValueError("onnx: Relu does not take the previous layer's output")
            expect = "linear"
        else:
            raise ValueError(f"onnx: node {op!r} is not allowed here (a decoder is MatMul or Gemm layers, "
                             "each with an optional bias Add, with Relu between them)")
        cur = node_outputs[0]
    if not weights or expect == "linear" or cur != outputs[0]:
        raise ValueError("onnx: the graph does not end with a layer that writes its output")
    if set(inits) != used:
        raise ValueError(f"onnx: initializers {sorted(set(inits) - used)} are not used")
    if len(weights) > MAX_LAYERS:
        raise ValueError(f"onnx: {len(weights)} layers, a decoder has at most {MAX_LAYERS}")
    for k in range(1, len(weights)):
        if weights[k].shape[1] != weights[k - 1].shape[0]:
            raise ValueError(f"onnx: layer {k} takes {weights[k].shape[1]} inputs, layer {k - 1} gives "
                             f"{weights[k - 1].shape[0]}")
    return MLP(tuple(weights), tuple(biases))


def canonical(data) -> bytes:
    """The canonical bytes of decoder `data` (read_mlp(data).to_onnx()): what a reader keeps and hands
    to onnxruntime. Graphs written by mlp_to_onnx come back unchanged. ValueError for invalid decoders."""
    return read_mlp(data).to_onnx()
