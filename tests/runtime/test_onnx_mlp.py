"""stg_runtime.onnx_mlp: the dependency-free ONNX codec for the colour decoder."""
import io

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from stg_runtime.onnx_mlp import check_graph, mlp_to_onnx, mlp_weights, parse, read_graph


def random_weights(rng, sizes=(12, 6, 3)):
    return [rng.standard_normal((o, i)).astype(np.float32) for i, o in zip(sizes[:-1], sizes[1:])]


def numpy_mlp(x, weights):
    for k, w in enumerate(weights):
        x = x @ w.T
        if k < len(weights) - 1:
            x = np.maximum(x, 0)
    return x


def helper_model(weights, raw=True, gemm=False, extra_nodes=(), extra_inits=(), inputs=None):
    """A MatMul (or Gemm transB=1) chain built with onnx.helper."""
    nodes, inits, cur = [], [], "x"
    for k, w in enumerate(weights):
        out = "y" if k == len(weights) - 1 else f"h{k}"
        if gemm:
            inits.append(numpy_helper.from_array(w, f"W{k}"))
            nodes.append(helper.make_node("Gemm", [cur, f"W{k}"], [out], transB=1))
        else:
            t = numpy_helper.from_array(np.ascontiguousarray(w.T), f"W{k}")
            if not raw:
                t = helper.make_tensor(f"W{k}", TensorProto.FLOAT, w.T.shape, w.T.ravel().tolist())
            inits.append(t)
            nodes.append(helper.make_node("MatMul", [cur, f"W{k}"], [out]))
        cur = out
        if out != "y":
            cur = f"a{k}"
            nodes.append(helper.make_node("Relu", [out], [cur]))
    inputs = inputs or [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["P", weights[0].shape[1]])]
    graph = helper.make_graph(nodes + list(extra_nodes), "g", inputs,
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["P", weights[-1].shape[0]])],
                              inits + list(extra_inits))
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def assert_weights_equal(got, want):
    assert got is not None and len(got) == len(want)
    for g, w in zip(got, want):
        assert g.dtype == np.float32 and g.shape == w.shape
        np.testing.assert_array_equal(g, w)


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
    check_graph(data)
    assert_weights_equal(mlp_weights(data), weights)


def test_mlp_to_onnx_rejects_bad_weights():
    with pytest.raises(ValueError):
        mlp_to_onnx([])
    with pytest.raises(ValueError):
        mlp_to_onnx([np.zeros((6, 12), np.float32), np.zeros((3, 5), np.float32)])
    with pytest.raises(ValueError):
        mlp_to_onnx([np.zeros(12, np.float32)])


@pytest.mark.parametrize("raw", [True, False])
def test_mlp_weights_from_onnx_helper(raw):
    weights = random_weights(np.random.default_rng(2))
    model = helper_model(weights, raw=raw)
    onnx.checker.check_model(model)
    assert_weights_equal(mlp_weights(model.SerializeToString()), weights)


def test_mlp_weights_from_gemm():
    weights = random_weights(np.random.default_rng(3))
    model = helper_model(weights, gemm=True)
    onnx.checker.check_model(model)
    assert_weights_equal(mlp_weights(model.SerializeToString()), weights)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_mlp_weights_from_torch_export():
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(12, 6, bias=False), torch.nn.ReLU(), torch.nn.Linear(6, 3, bias=False))
    buf = io.BytesIO()
    torch.onnx.export(net, (torch.zeros(4, 12),), buf, dynamo=False, input_names=["x"], output_names=["y"],
                      dynamic_axes={"x": {0: "P"}, "y": {0: "P"}})
    data = buf.getvalue()
    check_graph(data)
    assert_weights_equal(mlp_weights(data), [net[0].weight.detach().numpy(), net[2].weight.detach().numpy()])


def test_mlp_weights_refuses_other_graphs():
    rng = np.random.default_rng(4)
    weights = random_weights(rng)
    # a bias after the last layer: one node too many
    bias = numpy_helper.from_array(np.zeros(3, np.float32), "b")
    model = helper_model(weights)
    model.graph.node[-1].output[0] = "z"
    model.graph.node.append(helper.make_node("Add", ["z", "b"], ["y"]))
    model.graph.initializer.append(bias)
    assert mlp_weights(model.SerializeToString()) is None
    # Sigmoid instead of Relu
    model = helper_model(weights)
    model.graph.node[1].op_type = "Sigmoid"
    assert mlp_weights(model.SerializeToString()) is None
    # Gemm with alpha != 1
    model = helper_model(weights, gemm=True)
    model.graph.node[0].attribute.append(helper.make_attribute("alpha", 2.0))
    assert mlp_weights(model.SerializeToString()) is None
    # weights that are a graph input, not an initializer
    model = helper_model(weights)
    model.graph.initializer.pop(0)
    model.graph.input.append(helper.make_tensor_value_info("W0", TensorProto.FLOAT, [12, 6]))
    assert mlp_weights(model.SerializeToString()) is None


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


def test_check_graph_refuses_external_initializer(tmp_path):
    model = helper_model(random_weights(np.random.default_rng(5)))
    onnx.external_data_helper.convert_model_to_external_data(model, location="weights.bin", size_threshold=0)
    assert any(t.data_location == TensorProto.EXTERNAL for t in model.graph.initializer)
    with pytest.raises(ValueError, match="external"):
        check_graph(model.SerializeToString())
    # data_location alone, without external_data entries
    model = helper_model(random_weights(np.random.default_rng(5)))
    model.graph.initializer[1].data_location = TensorProto.EXTERNAL
    with pytest.raises(ValueError, match="external"):
        check_graph(model.SerializeToString())


def test_check_graph_refuses_external_data_in_nested_tensors():
    weights = random_weights(np.random.default_rng(6))
    const = numpy_helper.from_array(np.ones(3, np.float32), "c")
    const.data_location = TensorProto.EXTERNAL
    ext = const.external_data.add()
    ext.key, ext.value = "location", "elsewhere.bin"
    # a Constant node's tensor attribute
    model = helper_model(weights, extra_nodes=[helper.make_node("Constant", [], ["unused"], value=const)])
    with pytest.raises(ValueError, match="external"):
        check_graph(model.SerializeToString())
    # an initializer inside a subgraph attribute (If branch)
    branch = helper.make_graph([helper.make_node("Identity", ["c"], ["o"])], "branch", [],
                               [helper.make_tensor_value_info("o", TensorProto.FLOAT, [3])], [const])
    cond = numpy_helper.from_array(np.array(True), "cond")
    node = helper.make_node("If", ["cond"], ["unused"], then_branch=branch, else_branch=branch)
    model = helper_model(weights, extra_nodes=[node], extra_inits=[cond])
    with pytest.raises(ValueError, match="external"):
        check_graph(model.SerializeToString())


def test_check_graph_refuses_wrong_interface():
    weights = random_weights(np.random.default_rng(7))
    two_inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["P", 12]) for n in ("x", "x2")]
    with pytest.raises(ValueError, match="one input"):
        check_graph(helper_model(weights, inputs=two_inputs).SerializeToString())
    with pytest.raises(ValueError, match="no graph"):
        check_graph(onnx.ModelProto(ir_version=8).SerializeToString())
    # initializers listed as inputs (old exporters) do not count as inputs
    model = helper_model(weights)
    model.graph.input.append(helper.make_tensor_value_info("W0", TensorProto.FLOAT, [12, 6]))
    check_graph(model.SerializeToString())
    assert read_graph(model.SerializeToString()).inputs == ["x"]


def test_check_graph_refuses_garbage():
    rng = np.random.default_rng(8)
    for size in (0, 1, 7, 100, 1000):
        with pytest.raises(ValueError):
            check_graph(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
    good = mlp_to_onnx(random_weights(rng))
    for cut in range(1, len(good), 17):  # truncations: refused with ValueError, never another exception
        with pytest.raises(ValueError):
            check_graph(good[:cut])
    for _ in range(200):  # random byte flips: a ValueError or a pass, nothing else
        bad = bytearray(good)
        bad[rng.integers(len(bad))] = rng.integers(256)
        try:
            check_graph(bytes(bad))
        except ValueError:
            pass


def test_check_graph_deep_nesting_is_refused_without_recursion():
    def ld(field, payload):
        n, out = len(payload), bytearray([field << 3 | 2])
        while n >= 0x80:
            out.append(n & 0x7F | 0x80)
            n >>= 7
        return bytes(out + bytes([n])) + payload

    graph = b""
    for _ in range(500):  # graph -> node -> attribute -> graph -> ...
        graph = ld(1, ld(5, ld(6, graph)))
    with pytest.raises(ValueError, match="nested"):
        check_graph(ld(7, graph))
