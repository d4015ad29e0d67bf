#!/usr/bin/env python
"""Regenerate the hostile-input fixtures: crafted .stg files in tests/runtime/malicious/ and crafted PLYs
in tests/convert/malicious/, each folder with an index.json of what a reader must do with every file
("refused" with a message matching "match", or "loads" and renders). tests/runtime/test_malicious.py
and tests/convert/test_malicious.py check them. Needs the `onnx` package (the train extra).

    python tools/make_malicious_files.py
"""
from __future__ import annotations

import copy
import json
import zlib
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from craft import field, seal, split
from stg_runtime import Camera, Model, Segment
from stg_runtime import format as stg_format
from stg_runtime.onnx_mlp import mlp_to_onnx
from stg_train.convert.ply import write_ply

ROOT = Path(__file__).resolve().parent.parent
STG_DIR = ROOT / "tests" / "runtime" / "malicious"
PLY_DIR = ROOT / "tests" / "convert" / "malicious"


def _weights(seed=0, hidden=6):
    rng = np.random.default_rng(seed)
    return [rng.standard_normal((hidden, 12)).astype(np.float32) * 0.3,
            rng.standard_normal((3, hidden)).astype(np.float32) * 0.3]


def _base(kind="full", count=20) -> bytes:
    """A small honest model: one segment of `count` Gaussians in front of one 48x32 camera."""
    rng = np.random.default_rng(1)
    position = np.zeros((count, 4, 3))
    position[:, 0] = np.stack([rng.uniform(-1, 1, count), rng.uniform(-1, 1, count), rng.uniform(3, 5, count)], 1)
    segment = Segment(0, 4, opacity=rng.uniform(0.3, 0.9, count), t_center=rng.uniform(0, 1, count),
                      t_scale=np.zeros(count), position=position, rotation=np.tile([1.0, 0, 0, 0], (count, 2, 1)),
                      scale=np.full((count, 3), 0.2), features=rng.uniform(0, 1, (count, 9 if kind == "full" else 3)),
                      decoder=mlp_to_onnx(_weights()) if kind == "full" else None)
    camera = Camera.look_at([0, 0, 0], [0, 0, 4], [0, -1, 0], 50.0, 48, 32, name="cam00")
    return stg_format.dumps(Model(kind, 10.0, [segment], cameras=[camera]))


def _with_decoder(decoder: bytes) -> bytes:
    header, section, version = split(_base())
    header["segments"][0]["decoder"]["data"] = {"offset": len(section), "length": len(decoder), "codec": "raw"}
    return seal(header, section + decoder, version)


def _edited(edit, kind="full") -> bytes:
    header, section, version = split(_base(kind))
    edit(header)
    return seal(header, section, version)


def _segmented(edit, count=2) -> bytes:
    """The base model's segment repeated `count` times (4 frames each, the same blobs), `edit(segments)`
    applied to the header's segment list, as a version 1.3 file (per-segment context and crossfades)."""
    header, section, _ = split(_base())
    first = header["segments"][0]
    header["segments"] = [dict(copy.deepcopy(first), start_frame=4 * k) for k in range(count)]
    header["num_frames"] = 4 * count
    edit(header["segments"])
    return seal(header, section, (1, 3))


def _mlp_model(weights=None, **kw) -> onnx.ModelProto:
    return onnx.load_from_string(mlp_to_onnx(weights or _weights(), **kw))


def _decoder_key_bit32() -> bytes:
    """external_data (TensorProto field 13) spelled with key bit 32 set: what protobuf and onnxruntime
    read as field 13 (modulo 2^32) and a 70-bit-key reader skipped as unknown."""
    model = _mlp_model()
    entry = field(1, 2, b"location") + field(2, 2, b"weights.bin")
    tensor = model.graph.initializer[0].SerializeToString() + field(13, 2, entry, key_bits=1 << 32)
    graph = onnx.GraphProto()
    graph.CopyFrom(model.graph)
    del graph.initializer[0]
    rest = onnx.ModelProto()
    rest.CopyFrom(model)
    rest.ClearField("graph")
    return rest.SerializeToString() + field(7, 2, graph.SerializeToString() + field(5, 2, tensor))


def _decoder_external() -> bytes:
    model = _mlp_model()
    onnx.external_data_helper.convert_model_to_external_data(model, location="weights.bin", size_threshold=0)
    return model.SerializeToString()


def _decoder_unknown_op() -> bytes:
    model = _mlp_model()
    model.graph.node[1].op_type, model.graph.node[1].domain = "Exfiltrate", "com.example.evil"
    model.opset_import.append(helper.make_opsetid("com.example.evil", 1))
    return model.SerializeToString()


def _decoder_loop() -> bytes:
    """A Loop of 10^15 iterations beside the MLP (the render would hang)."""
    model = _mlp_model()
    body = helper.make_graph([helper.make_node("Identity", ["cond_in"], ["cond_out"])], "body",
                             [helper.make_tensor_value_info("i", TensorProto.INT64, []),
                              helper.make_tensor_value_info("cond_in", TensorProto.BOOL, [])],
                             [helper.make_tensor_value_info("cond_out", TensorProto.BOOL, [])])
    model.graph.initializer.extend([numpy_helper.from_array(np.array(10 ** 15, np.int64), "trips"),
                                    numpy_helper.from_array(np.array(True), "go")])
    model.graph.node.append(helper.make_node("Loop", ["trips", "go"], [], body=body))
    return model.SerializeToString()


def _decoder_constant_of_shape() -> bytes:
    """ConstantOfShape of 2^34 floats (64 GiB) feeding the output."""
    model = _mlp_model()
    model.graph.initializer.append(numpy_helper.from_array(np.array([1 << 34], np.int64), "huge"))
    model.graph.node[-1].output[0] = "z"
    model.graph.node.extend([helper.make_node("ConstantOfShape", ["huge"], ["big"]),
                             helper.make_node("Add", ["z", "big"], ["y"])])
    return model.SerializeToString()


def _decoder_second_input() -> bytes:
    model = _mlp_model()
    model.graph.input.append(helper.make_tensor_value_info("secret", TensorProto.FLOAT, ["P", 12]))
    return model.SerializeToString()


def _decoder_nan() -> bytes:
    weights = _weights()
    weights[0][2, 5] = np.nan
    return mlp_to_onnx(weights)


def _decoder_wide() -> bytes:
    return mlp_to_onnx(_weights(hidden=300))


def _decoder_declares(**fields) -> bytes:
    model = _mlp_model()
    if "opset" in fields:
        model.opset_import[0].version = fields["opset"]
    if "ir_version" in fields:
        model.ir_version = fields["ir_version"]
    if "output_width" in fields:
        model.graph.output[0].type.tensor_type.shape.dim[1].dim_value = fields["output_width"]
    return model.SerializeToString()


def _zlib_bomb() -> bytes:
    """A valid lite model of 2^20 Gaussians of zeros: about 120 MB in memory from a file of about 120 KB."""
    n = 1 << 20
    z = np.zeros
    segment = Segment(0, 1, opacity=z(n), t_center=z(n), t_scale=z(n), position=z((n, 4, 3)),
                      rotation=z((n, 2, 4)), scale=z((n, 3)), features=z((n, 3)))
    return stg_format.dumps(Model("lite", 30.0, [segment]), level=9)


COMPACT = {"features": "vq/f32", "position": "u16-delta:3+vq/f16:9", "opacity": "u8-delta"}


AC = {"features": "ac8:3+ac5-delta:6", "position": "ac12-delta:3+ac6:9", "opacity": "ac7"}


def _encoded(encodings: dict, version: tuple, edit=None, section_edit=None) -> bytes:
    """The base model written with `encodings` (raw blobs), `edit(header)` and
    `section_edit(header, section) -> section` applied, sealed as `version`."""
    header, section, _ = split(stg_format.dumps(stg_format.loads(_base()), encodings, codec="raw"))
    if edit:
        edit(header)
    if section_edit:
        section = section_edit(header, section)
    return seal(header, section, version)


def _compact(edit=None, section_edit=None) -> bytes:
    """(1.4) The base model with vq, parts and delta arrays."""
    return _encoded(COMPACT, (1, 4), edit, section_edit)


def _ac(edit=None, section_edit=None) -> bytes:
    """(1.5) The base model with arithmetic-coded arrays."""
    return _encoded(AC, (1, 5), edit, section_edit)


def _opacity(header):
    return header["segments"][0]["attributes"]["opacity"]


def _features(header):
    return header["segments"][0]["attributes"]["features"]


def _poke(spec, values: bytes):
    """A section edit: `values` written at the start of blob `spec(header)`."""
    def edit(header, section):
        at = spec(header)["data"]["offset"]
        return section[:at] + values + section[at + len(values):]
    return edit


def _codebook_bomb() -> bytes:
    """64 segments whose features index one shared, zlib-compressed codebook of 65536 rows of zeros:
    64 x 65536 x 9 float32 (151 MB) from a file of a few KB."""
    header, section, _ = split(stg_format.dumps(stg_format.loads(_base()), COMPACT, codec="raw"))
    zeros = zlib.compress(bytes(65536 * 9 * 4), 9)
    book = {"shape": [65536, 9], "encoding": "f32", "data": {"offset": len(section), "length": len(zeros),
                                                             "codec": "zlib"}}
    first = header["segments"][0]
    first["attributes"]["features"]["codebook"] = book
    header["segments"] = [dict(copy.deepcopy(first), start_frame=4 * k) for k in range(64)]
    header["num_frames"] = 4 * 64
    return seal(header, section + zeros, (1, 4))


def _set_count(header, count):
    s = header["segments"][0]
    s["count"] = count
    for name, spec in s["attributes"].items():
        spec["shape"][0] = count


def _set_camera(**values):
    def edit(header):
        header["cameras"][0].update(values)
    return edit


def stg_fixtures() -> dict[str, tuple[bytes, dict]]:
    refused = lambda match: {"expect": "refused", "match": match}  # noqa: E731
    loads = {"expect": "loads"}
    not_rigid = lambda h: h["cameras"][0]["world_to_camera"].__setitem__(0, 2.0)  # noqa: E731
    return {
        "decoder_key_bit32.stg": (_with_decoder(_decoder_key_bit32()), refused("decoder: .*32 bits")),
        "decoder_external_data.stg": (_with_decoder(_decoder_external()), refused("decoder: .*external data")),
        "decoder_unknown_op.stg": (_with_decoder(_decoder_unknown_op()), refused("decoder: .*domain")),
        "decoder_loop.stg": (_with_decoder(_decoder_loop()), refused("decoder: ")),
        "decoder_constant_of_shape.stg": (_with_decoder(_decoder_constant_of_shape()), refused("decoder: ")),
        "decoder_second_input.stg": (_with_decoder(_decoder_second_input()), refused("decoder: .*one input")),
        "decoder_nan_weights.stg": (_with_decoder(_decoder_nan()), refused("decoder: .*non-finite")),
        "decoder_too_wide.stg": (_with_decoder(_decoder_wide()), refused("decoder: .*dims")),
        "decoder_opset_999.stg": (_with_decoder(_decoder_declares(opset=999)), loads),
        "decoder_ir_version_99.stg": (_with_decoder(_decoder_declares(ir_version=99)), loads),
        "decoder_lying_output_width.stg": (_with_decoder(_decoder_declares(output_width=5)), loads),
        "zlib_bomb.stg": (_zlib_bomb(), refused("would take .* bytes in memory")),
        "count_2_26.stg": (_edited(lambda h: _set_count(h, 1 << 26)), refused("67108864 Gaussians, more than")),
        "degree_1e9.stg": (_edited(lambda h: h["segments"][0].update(position_degree=10 ** 9)),
                           refused("degrees 1000000000")),
        "frames_1e15.stg": (_edited(lambda h: (h["segments"][0].update(num_frames=10 ** 15),
                                               h.update(num_frames=10 ** 15))), refused("beyond the reader's limit")),
        "camera_width_1e21.stg": (_edited(_set_camera(width=10 ** 21)), refused("camera 0: .*exceeds")),
        "camera_fx_5e-324.stg": (_edited(_set_camera(fx=5e-324)), refused("camera 0: .*focal")),
        "camera_not_rigid.stg": (_edited(not_rigid), refused("camera 0: .*rigid")),
        # format 1.3: context_frames and crossfade_frames (formats/stg-v1.md, "Segments and crossfades")
        "crossfade_first_segment.stg": (_segmented(lambda s: s[0].update(crossfade_frames=2)),
                                        refused("segment 0 has crossfade_frames, but no segment before it")),
        "crossfade_overlapping.stg": (_segmented(lambda s: (s[1].update(crossfade_frames=5),
                                                            s[2].update(crossfade_frames=4)), count=3),
                                      refused(r"segment 1 \(4 frames\) is too short for its crossfades "
                                              r"\(5 in, 4 out\)")),
        "crossfade_frames_float.stg": (_segmented(lambda s: s[1].update(crossfade_frames=2.5)),
                                       refused("segment 1: crossfade_frames must be an integer in")),
        "crossfade_frames_string.stg": (_segmented(lambda s: s[1].update(crossfade_frames="2")),
                                        refused("segment 1: crossfade_frames must be an integer in")),
        "context_frames_negative.stg": (_segmented(lambda s: s[0].update(context_frames=[0, -1])),
                                        refused("segment 0: context_frames must be a list of two integers")),
        "context_frames_float.stg": (_segmented(lambda s: s[1].update(context_frames=[1.5, 0])),
                                     refused("segment 1: context_frames must be a list of two integers")),
        "context_frames_bool.stg": (_segmented(lambda s: s[0].update(context_frames=[0, True])),
                                    refused("segment 0: context_frames must be a list of two integers")),
        "context_frames_2_24_plus_1.stg": (_segmented(lambda s: s[0].update(context_frames=[0, 2 ** 24 + 1])),
                                           refused("segment 0: context_frames must be a list of two integers")),
        # the largest crossfade two 4-frame segments allow (8 frames: all of both); t = 0 is inside it
        "crossfade_at_the_limit.stg": (_segmented(lambda s: (s[0].update(context_frames=[0, 4]),
                                                             s[1].update(context_frames=[4, 0], crossfade_frames=8))),
                                       loads),
        # format 1.4: differences, codebooks and parts (formats/stg-v1.md, "Deltas, codebooks and parts")
        "compact_arrays.stg": (_compact(), loads),
        "vq_index_beyond_codebook.stg": (_compact(section_edit=_poke(_features, bytes([20]))),
                                         refused("attribute 'features': index 20 beyond the codebook's 20 rows")),
        "vq_codebook_65537_rows.stg": (_compact(lambda h: _features(h)["codebook"].update(shape=[65537, 9])),
                                       refused(r"codebook's shape must be \[K, 9\] with K in \[1, 65536\]")),
        "vq_codebook_nan.stg": (_compact(section_edit=_poke(lambda h: _features(h)["codebook"],
                                                            np.float32([np.nan]).tobytes())),
                                refused("attribute 'features': decoded values are not all finite")),
        "vq_in_a_codebook.stg": (_compact(lambda h: _features(h)["codebook"].update(
            encoding="vq", codebook={"shape": [1, 9], "encoding": "f32", "data": {"offset": 0, "length": 36,
                                                                                  "codec": "raw"}})),
            refused("codebook: unknown encoding 'vq' \\(not allowed in a codebook\\)")),
        "parts_in_a_part.stg": (_compact(lambda h: h["segments"][0]["attributes"]["position"]["parts"][0].update(
            encoding="parts", parts=[])), refused("part 0: unknown encoding 'parts' \\(not allowed in a part\\)")),
        "parts_cover_too_few.stg": (_compact(lambda h: h["segments"][0]["attributes"]["position"]["parts"].pop()),
                                    refused("the parts cover 3 channels, the array has 12")),
        "codebook_bomb.stg": (_codebook_bomb(), refused("would take .* bytes in memory")),
        # format 1.5: arithmetic-coded fixed point (formats/stg-v1.md, "Arithmetic-coded fixed point")
        "ac_arrays.stg": (_ac(), loads),
        "ac_zlib_blob.stg": (_ac(lambda h: _opacity(h)["data"].update(codec="zlib")),
                             refused("attribute 'opacity': unsupported codec 'zlib'")),
        "ac_first_byte_1.stg": (_ac(section_edit=_poke(_opacity, bytes([1]))),
                                refused("attribute 'opacity': arithmetic-coded data must start with a 0 byte")),
        "ac_cut_short.stg": (_ac(lambda h: _opacity(h)["data"].update(length=_opacity(h)["data"]["length"] - 1)),
                             refused("attribute 'opacity': arithmetic-coded data ends before its 20 values")),
        "ac_byte_after.stg": (_ac(lambda h: _opacity(h)["data"].update(length=_opacity(h)["data"]["length"] + 1)),
                              refused("attribute 'opacity': arithmetic-coded data has 1 bytes after its 20 values")),
        "ac_17_bits.stg": (_ac(lambda h: _opacity(h).update(encoding="ac17")),
                           refused("attribute 'opacity': unknown encoding 'ac17'")),
        "ac_leading_zero.stg": (_ac(lambda h: _opacity(h).update(encoding="ac07")),
                                refused("attribute 'opacity': unknown encoding 'ac07'")),
        "ac_without_scale.stg": (_ac(lambda h: _opacity(h).pop("scale")),
                                 refused("attribute 'opacity': ac7 needs lists 'offset' and 'scale' of 1 numbers")),
    }


def _ply_header(*lines, fmt="binary_little_endian") -> bytes:
    return ("\n".join(["ply", f"format {fmt} 1.0", *lines, "end_header"]) + "\n").encode()


def ply_fixtures(folder: Path) -> dict[str, dict]:
    xyz = ["property float x", "property float y", "property float z"]
    files = {
        "vertex_count_1e9.ply": (_ply_header("element vertex 1000000000", *xyz) + bytes(12), "truncated"),
        "vertex_count_1e20.ply": (_ply_header("element vertex 100000000000000000000", *xyz) + bytes(12), "truncated"),
        "element_before_vertex_1e20.ply": (_ply_header("element face 100000000000000000000", "property uchar a",
                                                       "element vertex 1", *xyz) + bytes(12), "element 'face'"),
        "ascii_uchar_300.ply": (_ply_header("element vertex 1", "property uchar red", fmt="ascii") + b"300\n",
                                "out of range"),
        "list_in_vertex.ply": (_ply_header("element vertex 1", "property list uchar int idx") + bytes(5), "list"),
    }
    index = {}
    for name, (data, match) in files.items():
        (folder / name).write_bytes(data)
        index[name] = {"expect": "refused", "match": match}
    # a 3DGS PLY whose x is a double of 1e300: finite in the file, not in a model
    rng = np.random.default_rng(0)
    props = {"x": np.array([1e300, 0.0]), "y": np.zeros(2, np.float32), "z": np.ones(2, np.float32),
             **{f"{p}": np.zeros(2, np.float32) for p in ("nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                                                          "scale_0", "scale_1", "scale_2", "rot_1", "rot_2", "rot_3")},
             "rot_0": rng.uniform(0.5, 1, 2).astype(np.float32)}
    write_ply(folder / "gaussians_x_1e300.ply", props)
    index["gaussians_x_1e300.ply"] = {"expect": "refused", "match": "'x' has values that are not finite float32"}
    return index


def main() -> None:
    STG_DIR.mkdir(parents=True, exist_ok=True)
    PLY_DIR.mkdir(parents=True, exist_ok=True)
    index = {}
    for name, (data, expect) in stg_fixtures().items():
        (STG_DIR / name).write_bytes(data)
        index[name] = expect
    (STG_DIR / "index.json").write_text(json.dumps(index, indent=1) + "\n")
    (PLY_DIR / "index.json").write_text(json.dumps(ply_fixtures(PLY_DIR), indent=1) + "\n")
    total = sum(p.stat().st_size for p in list(STG_DIR.iterdir()) + list(PLY_DIR.iterdir()))
    print(f"wrote {len(index)} .stg files to {STG_DIR} and the PLYs to {PLY_DIR} ({total} bytes)")


if __name__ == "__main__":
    main()
