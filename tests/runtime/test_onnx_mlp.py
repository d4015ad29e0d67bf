"""stg_runtime.onnx_mlp: the dependency-free codec of the decoder graphs, and the strict reader that
accepts exactly the MLP family of formats/stg-v1.md (section 2)."""
import io

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from stg_runtime.onnx_mlp import MAX_LAYERS, MAX_WIDTH, canonical, mlp_to_onnx, parse, read_mlp


def random_weights(rng, sizes=(12, 6, 3)):
    return [rng.standard_normal((o, i)).astype(np.float32) for i, o in zip(sizes[:-1], sizes[1:])]


def numpy_mlp(x, weights, biases=None):
    biases = biases or [None] * len(weights)
    for k, (w, b) in enumerate(zip(weights, biases)):
        x = x @ w.T + (0 if b is None else b)
        if k < len(weights) - 1:
            x = np.maximum(x, 0)
    return x


def helper_model(weights, raw=True, gemm=False, extra_nodes=(), extra_inits=(), inputs=None, biases=None):
    """A MatMul (or Gemm transB=1) chain built with onnx.helper; biases as Gemm's C or an Add node."""
    nodes, inits, cur = [], [], "x"
    biases = biases or [None] * len(weights)
    for k, (w, b) in enumerate(zip(weights, biases)):
        last = k == len(weights) - 1
        out = "y" if last and (b is None or gemm) else f"h{k}"
        if gemm:
            inits.append(numpy_helper.from_array(w, f"W{k}"))
            args = [cur, f"W{k}"]
            if b is not None:
                inits.append(numpy_helper.from_array(b, f"B{k}"))
                args.append(f"B{k}")
            nodes.append(helper.make_node("Gemm", args, [out], transB=1))
        else:
            t = numpy_helper.from_array(np.ascontiguousarray(w.T), f"W{k}")
            if not raw:
                t = helper.make_tensor(f"W{k}", TensorProto.FLOAT, w.T.shape, w.T.ravel().tolist())
            inits.append(t)
            nodes.append(helper.make_node("MatMul", [cur, f"W{k}"], [out]))
            if b is not None:
                inits.append(numpy_helper.from_array(b, f"B{k}"))
                cur, out = out, "y" if last else f"s{k}"
                nodes.append(helper.make_node("Add", [f"B{k}", cur], [out]))
        cur = out
        if not last:
            cur = f"a{k}"
            nodes.append(helper.make_node("Relu", [out], [cur]))
    inputs = inputs or [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["P", weights[0].shape[1]])]
    graph = helper.make_graph(nodes + list(extra_nodes), "g", inputs,
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["P", weights[-1].shape[0]])],
                              inits + list(extra_inits))
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def assert_mlp(got, weights, biases=None):
    biases = biases or [None] * len(weights)
    assert len(got.weights) == len(weights)
    for g, w in zip(got.weights, weights):
        assert g.dtype == np.float32 and g.shape == w.shape
        np.testing.assert_array_equal(g, w)
    for g, b in zip(got.biases, biases):
        assert (g is None) == (b is None)
        if b is not None:
            np.testing.assert_array_equal(g, b)


@pytest.mark.parametrize("sizes", [(12, 6, 3), (12, 3), (5, 7, 4, 3)])
def test_mlp_to_onnx_is_valid_and_matches_numpy(sizes):
    weights = random_weights(np.random.default_rng(0), sizes)
    data = mlp_to_onnx(weights)
    model = onnx.load_from_string(data)
    onnx.checker.check_model(model, full_check=True)
    assert model.ir_version == 8 and model.producer_name == "stg_runtime"
    assert [(o.domain, o.version) for o in model.opset_import] == [("", 17)]
    assert [n.op_type for n in model.graph.node] == ["MatMul", "Relu"] * (len(sizes) - 2) + ["MatMul"]
    assert all(t.HasField("raw_data") for t in model.graph.initializer)
    (inp,), (out,) = model.graph.input, model.graph.output
    assert [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim] == ["P", sizes[0]]
    assert [d.dim_param or d.dim_value for d in out.type.tensor_type.shape.dim] == ["P", sizes[-1]]
    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    x = np.random.default_rng(1).standard_normal((33, sizes[0])).astype(np.float32)
    (y,) = session.run(None, {"x": x})
    np.testing.assert_allclose(y, numpy_mlp(x.astype(np.float64), weights), atol=1e-5, rtol=1e-5)
    assert_mlp(read_mlp(data), weights)
    assert canonical(data) == data  # our own graphs are already canonical: files keep their bytes


def test_biases_round_trip_and_run():
    rng = np.random.default_rng(9)
    weights = random_weights(rng, (12, 8, 3))
    biases = [rng.standard_normal(8).astype(np.float32), rng.standard_normal(3).astype(np.float32)]
    data = mlp_to_onnx(weights, biases)
    onnx.checker.check_model(onnx.load_from_string(data), full_check=True)
    assert_mlp(read_mlp(data), weights, biases)
    x = rng.standard_normal((9, 12)).astype(np.float32)
    (y,) = ort.InferenceSession(data, providers=["CPUExecutionProvider"]).run(None, {"x": x})
    np.testing.assert_allclose(y, numpy_mlp(x.astype(np.float64), weights, biases), atol=1e-5, rtol=1e-5)
    for gemm in (False, True):  # the same MLP written by onnx.helper: Add nodes or Gemm's C
        other = helper_model(weights, gemm=gemm, biases=biases).SerializeToString()
        assert_mlp(read_mlp(other), weights, biases)
        assert canonical(other) == data


def test_mlp_to_onnx_rejects_bad_weights():
    with pytest.raises(ValueError):
        mlp_to_onnx([])
    with pytest.raises(ValueError):
        mlp_to_onnx([np.zeros((6, 12), np.float32), np.zeros((3, 5), np.float32)])
    with pytest.raises(ValueError):
        mlp_to_onnx([np.zeros(12, np.float32)])
    with pytest.raises(ValueError):
        mlp_to_onnx([np.zeros((3, 12), np.float32)], [np.zeros(4, np.float32)])


@pytest.mark.parametrize("raw", [True, False])
def test_read_mlp_from_onnx_helper(raw):
    weights = random_weights(np.random.default_rng(2))
    model = helper_model(weights, raw=raw)
    onnx.checker.check_model(model)
    assert_mlp(read_mlp(model.SerializeToString()), weights)


def test_read_mlp_from_gemm():
    weights = random_weights(np.random.default_rng(3))
    model = helper_model(weights, gemm=True)
    onnx.checker.check_model(model)
    assert_mlp(read_mlp(model.SerializeToString()), weights)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("bias", [False, True])
def test_read_mlp_from_torch_export(bias):
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(12, 6, bias=bias), torch.nn.ReLU(), torch.nn.Linear(6, 3, bias=bias))
    buf = io.BytesIO()
    torch.onnx.export(net, (torch.zeros(4, 12),), buf, dynamo=False, input_names=["x"], output_names=["y"],
                      dynamic_axes={"x": {0: "P"}, "y": {0: "P"}})
    got = read_mlp(buf.getvalue())
    assert_mlp(got, [net[0].weight.detach().numpy(), net[2].weight.detach().numpy()],
               [net[0].bias.detach().numpy(), net[2].bias.detach().numpy()] if bias else None)


def _refused(model, match):
    with pytest.raises(ValueError, match=match):
        read_mlp(model.SerializeToString() if hasattr(model, "SerializeToString") else model)


def test_read_mlp_refuses_other_graphs():
    rng = np.random.default_rng(4)
    weights = random_weights(rng)
    model = helper_model(weights)
    model.graph.node[1].op_type = "Sigmoid"  # another activation
    _refused(model, "not allowed")
    model = helper_model(weights, gemm=True)
    model.graph.node[0].attribute.append(helper.make_attribute("alpha", 2.0))
    _refused(model, "Gemm attributes")
    model = helper_model(weights)  # weights that are a graph input, not an initializer
    model.graph.initializer.pop(0)
    model.graph.input.append(helper.make_tensor_value_info("W0", TensorProto.FLOAT, [12, 6]))
    _refused(model, "one input")
    model = helper_model(weights)  # a trailing Relu
    model.graph.node[-1].output[0] = "z"
    model.graph.node.append(helper.make_node("Relu", ["z"], ["y"]))
    _refused(model, "does not end")
    model = helper_model(weights, extra_inits=[numpy_helper.from_array(np.ones(3, np.float32), "spare")])
    _refused(model, "not used")
    model = helper_model(weights)
    model.graph.node[0].domain = "com.microsoft"
    _refused(model, "domain")
    model = helper_model(weights)
    model.graph.initializer[0].CopyFrom(numpy_helper.from_array(np.ascontiguousarray(weights[0].T).astype(np.float64), "W0"))
    _refused(model, "not float32")
    bad = weights[0].copy()
    bad[2, 3] = np.nan
    _refused(helper_model([bad, weights[1]]), "non-finite")
    _refused(helper_model(random_weights(rng, (12, MAX_WIDTH + 1, 3))), "dims")
    _refused(helper_model(random_weights(rng, (12,) + (4,) * MAX_LAYERS + (3,))), "at most")
    _refused(helper_model(weights, biases=[np.ones((6, 1), np.float32), None]), "bias of shape")
    with pytest.raises(ValueError, match="no graph"):
        read_mlp(onnx.ModelProto(ir_version=8).SerializeToString())


def test_read_mlp_refuses_fields_outside_the_spec():
    weights = random_weights(np.random.default_rng(10))
    model = helper_model(weights)
    model.training_info.add()  # ModelProto field 20
    _refused(model, "field 20")
    model = helper_model(weights)
    model.graph.sparse_initializer.add()  # GraphProto field 15
    _refused(model, "graph field 15")
    model = helper_model(weights)
    model.graph.node[0].attribute.append(helper.make_attribute("note", "text"))  # a string attribute
    _refused(model, "attribute field 4")


def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    return bytes(out + bytes([value]))


def _key(field: int, wire: int, high_bit: bool = False) -> bytes:
    return _varint((field << 3 | wire) | ((1 << 32) if high_bit else 0))


def _with_tensor_field(model, extra: bytes) -> bytes:
    """The model's bytes with `extra` appended to its first initializer (enclosing lengths rebuilt)."""
    tensor = model.graph.initializer[0].SerializeToString() + extra
    graph = onnx.GraphProto()
    graph.CopyFrom(model.graph)
    del graph.initializer[0]
    graph_bytes = graph.SerializeToString() + _key(5, 2) + _varint(len(tensor)) + tensor
    rest = onnx.ModelProto()
    rest.CopyFrom(model)
    rest.ClearField("graph")
    return rest.SerializeToString() + _key(7, 2) + _varint(len(graph_bytes)) + graph_bytes


def test_the_32_bit_key_bypass_is_refused():
    """A tensor field key with bit 32 set is field 13 (external_data) to protobuf and onnxruntime, which
    read keys modulo 2^32: to this reader it must be an error, not an unknown field to skip."""
    model = helper_model(random_weights(np.random.default_rng(11)))
    entry = b"\x0a\x08location\x12\x0bweights.bin"  # StringStringEntryProto {key, value}
    with pytest.raises(ValueError, match="32 bits"):
        read_mlp(_with_tensor_field(model, _key(13, 2, high_bit=True) + bytes([len(entry)]) + entry))
    with pytest.raises(ValueError, match="tensor field 13"):  # the same field, spelled plainly
        read_mlp(_with_tensor_field(model, _key(13, 2) + bytes([len(entry)]) + entry))
    assert read_mlp(_with_tensor_field(model, b"")).input_width == 12  # the rebuilt model itself is fine


def test_parse_wire_types():
    # field 1 varint 150, field 2 fixed64, field 3 bytes "abc", field 4 fixed32, field 1 again
    data = b"\x08\x96\x01" + b"\x11" + bytes(range(8)) + b"\x1a\x03abc" + b"\x25\x01\x02\x03\x04" + b"\x08\x01"
    fields = parse(data)
    assert fields[1] == [150, 1]
    assert fields[2] == [bytes(range(8))]
    assert bytes(fields[3][0]) == b"abc"
    assert fields[4] == [b"\x01\x02\x03\x04"]


@pytest.mark.parametrize("bad", [b"\x08", b"\x08\xff", b"\x1a\x05ab", b"\x11\x00", b"\x0b", b"\x00\x01",
                                 b"\x08" + b"\xff" * 11])
def test_parse_refuses_malformed(bad):
    with pytest.raises(ValueError):
        parse(bad)


def test_external_initializers_are_refused(tmp_path):
    model = helper_model(random_weights(np.random.default_rng(5)))
    onnx.external_data_helper.convert_model_to_external_data(model, location="weights.bin", size_threshold=0)
    assert any(t.data_location == TensorProto.EXTERNAL for t in model.graph.initializer)
    with pytest.raises(ValueError, match="field 13|external"):
        read_mlp(model.SerializeToString())
    # data_location alone, without external_data entries
    model = helper_model(random_weights(np.random.default_rng(5)))
    model.graph.initializer[1].data_location = TensorProto.EXTERNAL
    with pytest.raises(ValueError, match="external"):
        read_mlp(model.SerializeToString())


def test_nested_tensors_and_subgraphs_are_refused():
    weights = random_weights(np.random.default_rng(6))
    const = numpy_helper.from_array(np.ones(3, np.float32), "c")
    const.data_location = TensorProto.EXTERNAL
    ext = const.external_data.add()
    ext.key, ext.value = "location", "elsewhere.bin"
    # a Constant node's tensor attribute
    model = helper_model(weights, extra_nodes=[helper.make_node("Constant", [], ["unused"], value=const)])
    with pytest.raises(ValueError, match="attribute field 5"):
        read_mlp(model.SerializeToString())
    # an initializer inside a subgraph attribute (If branch)
    branch = helper.make_graph([helper.make_node("Identity", ["c"], ["o"])], "branch", [],
                               [helper.make_tensor_value_info("o", TensorProto.FLOAT, [3])], [const])
    cond = numpy_helper.from_array(np.array(True), "cond")
    node = helper.make_node("If", ["cond"], ["unused"], then_branch=branch, else_branch=branch)
    model = helper_model(weights, extra_nodes=[node], extra_inits=[cond])
    with pytest.raises(ValueError, match="not float32"):  # the If's bool condition is refused first
        read_mlp(model.SerializeToString())
    model = helper_model(weights, extra_nodes=[node])
    model.graph.input.append(helper.make_tensor_value_info("cond", TensorProto.BOOL, []))
    with pytest.raises(ValueError, match="attribute field 6|one input"):
        read_mlp(model.SerializeToString())


def test_wrong_interface_is_refused():
    weights = random_weights(np.random.default_rng(7))
    two_inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["P", 12]) for n in ("x", "x2")]
    with pytest.raises(ValueError, match="one input"):
        read_mlp(helper_model(weights, inputs=two_inputs).SerializeToString())
    # initializers listed as inputs (old exporters) do not count as inputs
    model = helper_model(weights)
    model.graph.input.append(helper.make_tensor_value_info("W0", TensorProto.FLOAT, [12, 6]))
    assert_mlp(read_mlp(model.SerializeToString()), weights)


def test_garbage_is_refused_with_value_error_only():
    rng = np.random.default_rng(8)
    for size in (0, 1, 7, 100, 1000):
        with pytest.raises(ValueError):
            read_mlp(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
    good = mlp_to_onnx(random_weights(rng))
    for cut in range(1, len(good), 17):  # truncations: refused with ValueError, never another exception
        with pytest.raises(ValueError):
            read_mlp(good[:cut])
    for _ in range(200):  # random byte flips: a ValueError or a pass, nothing else
        bad = bytearray(good)
        bad[rng.integers(len(bad))] = rng.integers(256)
        try:
            read_mlp(bytes(bad))
        except ValueError:
            pass


def test_deep_nesting_is_refused_without_recursion():
    def ld(field, payload):
        n, out = len(payload), bytearray([field << 3 | 2])
        while n >= 0x80:
            out.append(n & 0x7F | 0x80)
            n >>= 7
        return bytes(out + bytes([n])) + payload

    graph = b""
    for _ in range(500):  # graph -> node -> attribute -> graph -> ...
        graph = ld(1, ld(5, ld(6, graph)))
    with pytest.raises(ValueError, match="one input"):  # refused before any nested message is read
        read_mlp(ld(7, graph))
