// The decoder graph of formats/stg-v1.md, section 2 ("The decoder graph"): an ONNX ModelProto read as
// the MLP family and nothing else. The JavaScript twin of stg_runtime/onnx_mlp.py's read_mlp, with the
// same rules and messages; field numbers are those of onnx/onnx.proto.
//
//   readMlp(bytes: Uint8Array) -> {weights: [{rows: out, cols: in, data: Float32Array (out x in, row-major)}],
//                                   biases: [Float32Array (out) | null], inputWidth, outputWidth}
// Throws Error (message starting "onnx: " or "protobuf: ") for anything that is not a valid decoder.

const VARINT = 0, I64 = 1, LEN = 2, I32 = 5;
const FLOAT = 1;
export const MAX_LAYERS = 8;
export const MAX_WIDTH = 256;

function readVarint(buf, pos) {
  // Returns [value as a Number (exact below 2^53; larger values only need to compare as large), pos].
  let result = 0, shift = 0;
  for (;;) {
    if (pos >= buf.length) throw new Error("protobuf: truncated varint");
    const byte = buf[pos++];
    if (shift === 63 && byte > 1) throw new Error("protobuf: varint beyond 64 bits");
    result += (byte & 0x7f) * 2 ** shift;
    if (byte < 0x80) return [result, pos];
    shift += 7;
    if (shift >= 70) throw new Error("protobuf: varint longer than 10 bytes");
  }
}

function signed(v) { return v >= 2 ** 63 ? v - 2 ** 64 : v; }

/** The fields of one protobuf message: field number -> values in wire order (Numbers, or Uint8Array views). */
export function parse(buf) {
  const fields = new Map();
  let pos = 0;
  while (pos < buf.length) {
    let key;
    [key, pos] = readVarint(buf, pos);
    if (key >= 2 ** 32) throw new Error("protobuf: field key beyond 32 bits");
    const number = Math.floor(key / 8), wire = key % 8;
    if (number === 0) throw new Error("protobuf: field number 0");
    let value;
    if (wire === VARINT) {
      [value, pos] = readVarint(buf, pos);
    } else if (wire === I64 || wire === I32 || wire === LEN) {
      let size;
      if (wire === LEN) [size, pos] = readVarint(buf, pos);
      else size = wire === I64 ? 8 : 4;
      if (pos + size > buf.length) throw new Error(`protobuf: field ${number} runs past the end of the message`);
      value = { bytes: buf.subarray(pos, pos + size), wire };
      pos += size;
    } else {
      throw new Error(`protobuf: unsupported wire type ${wire} (field ${number})`);
    }
    if (!fields.has(number)) fields.set(number, []);
    fields.get(number).push(value);
  }
  return fields;
}

const FIELDS = {
  model: { 1: [VARINT, "ir_version"], 2: [LEN, "producer_name"], 3: [LEN, "producer_version"], 4: [LEN, "domain"],
    5: [VARINT, "model_version"], 6: [LEN, "doc_string"], 7: [LEN, "graph"], 8: [LEN, "opset_import"],
    14: [LEN, "metadata_props"] },
  opset: { 1: [LEN, "domain"], 2: [VARINT, "version"] },
  graph: { 1: [LEN, "node"], 2: [LEN, "name"], 5: [LEN, "initializer"], 10: [LEN, "doc_string"], 11: [LEN, "input"],
    12: [LEN, "output"], 13: [LEN, "value_info"] },
  node: { 1: [LEN, "input"], 2: [LEN, "output"], 3: [LEN, "name"], 4: [LEN, "op_type"], 5: [LEN, "attribute"],
    6: [LEN, "doc_string"], 7: [LEN, "domain"] },
  attribute: { 1: [LEN, "name"], 2: [I32, "f"], 3: [VARINT, "i"], 13: [LEN, "doc_string"], 20: [VARINT, "type"] },
  tensor: { 1: [VARINT, "dims"], 2: [VARINT, "data_type"], 4: [LEN, "float_data"], 8: [LEN, "name"], 9: [LEN, "raw_data"],
    12: [LEN, "doc_string"], 14: [VARINT, "data_location"] },
  value_info: { 1: [LEN, "name"], 2: [LEN, "type"], 3: [LEN, "doc_string"] },
};
const FORBIDDEN = { "tensor 13": "refers to external data", "graph 15": "has sparse initializers",
  "model 20": "has training information", "model 25": "has local functions", "attribute 5": "holds a tensor",
  "attribute 6": "holds a subgraph", "attribute 11": "holds subgraphs", "node 8": "names an overload" };
const SINGULAR = new Set(["graph", "name", "op_type", "domain", "data_type", "raw_data", "data_location", "f", "i",
  "type", "ir_version", "version"]);

function message(raw, kind) {
  const out = {};
  for (const [number, values] of parse(raw)) {
    const spec = FIELDS[kind][number];
    if (!spec) throw new Error(`onnx: ${kind} field ${number} ${FORBIDDEN[`${kind} ${number}`] || "is not allowed in a decoder"}`);
    const [wire, name] = spec;
    const ok = values.every((v) => {
      if (name === "float_data") return typeof v === "object" && (v.wire === LEN || v.wire === I32);
      if (name === "dims") return typeof v === "number" || v.wire === LEN;
      if (wire === VARINT) return typeof v === "number";
      return typeof v === "object" && v.wire === wire && (wire !== I32 || v.bytes.length === 4);
    });
    if (!ok) throw new Error(`onnx: ${kind} field ${name} has the wrong wire type`);
    if (SINGULAR.has(name) && values.length > 1) throw new Error(`onnx: ${kind} field ${name} is repeated`);
    out[name] = values.map((v) => (typeof v === "number" ? v : v.bytes));
  }
  return out;
}

const utf8 = new TextDecoder("utf-8", { fatal: true });
function text(fields, name) {
  const values = fields[name];
  return values && values.length ? utf8.decode(values[values.length - 1]) : "";
}

function ints(values) {
  const out = [];
  for (const v of values) {
    if (typeof v === "number") { out.push(signed(v)); continue; }
    let pos = 0, value;
    while (pos < v.length) { [value, pos] = readVarint(v, pos); out.push(signed(value)); }
  }
  return out;
}

function concat(parts) {
  const n = parts.reduce((s, p) => s + p.length, 0), out = new Uint8Array(n);
  let at = 0;
  for (const p of parts) { out.set(p, at); at += p.length; }
  return out;
}

function tensor(raw) {
  const t = message(raw, "tensor");
  const name = text(t, "name");
  if ((t.data_type ? t.data_type[0] : 0) !== FLOAT) throw new Error(`onnx: initializer '${name}' is not float32`);
  if ((t.data_location ? t.data_location[0] : 0) !== 0) throw new Error(`onnx: initializer '${name}' refers to external data`);
  const dims = ints(t.dims || []);
  if (dims.length < 1 || dims.length > 2 || dims.some((d) => d < 1 || d > MAX_WIDTH)) {
    throw new Error(`onnx: initializer '${name}' has dims [${dims.join(", ")}]; a decoder's weights are 1-D or 2-D, `
      + `each dimension 1..${MAX_WIDTH}`);
  }
  if (t.raw_data && t.float_data) throw new Error(`onnx: initializer '${name}' has both raw_data and float_data`);
  const bytes = t.raw_data ? t.raw_data[0] : concat(t.float_data || []);
  const size = dims.reduce((a, b) => a * b, 1);
  if (bytes.length !== 4 * size) {
    throw new Error(`onnx: initializer '${name}' holds ${bytes.length} bytes, its dims [${dims.join(", ")}] need ${4 * size}`);
  }
  const data = new Float32Array(size), view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  for (let k = 0; k < size; k++) {
    data[k] = view.getFloat32(4 * k, true);
    if (!Number.isFinite(data[k])) throw new Error(`onnx: initializer '${name}' has non-finite values`);
  }
  return [name, { dims, data }];
}

function attributes(node) {
  const out = {};
  for (const raw of node.attribute || []) {
    const a = message(raw, "attribute");
    const name = text(a, "name");
    if (name in out) throw new Error(`onnx: attribute '${name}' is repeated`);
    if (("f" in a) === ("i" in a)) throw new Error(`onnx: attribute '${name}' must hold one number`);
    out[name] = "f" in a ? new DataView(a.f[0].buffer, a.f[0].byteOffset, 4).getFloat32(0, true) : signed(a.i[0]);
  }
  return out;
}

function transpose(t) {  // (r, c) -> (c, r)
  const [r, c] = t.dims, out = new Float32Array(r * c);
  for (let i = 0; i < r; i++) for (let j = 0; j < c; j++) out[j * r + i] = t.data[i * c + j];
  return { rows: c, cols: r, data: out };
}

function bias(t, width) {
  const d = t.dims;
  if (!((d.length === 1 && d[0] === width) || (d.length === 2 && d[0] === 1 && d[1] === width))) {
    throw new Error(`onnx: a bias of shape [${d.join(", ")}] for a layer of ${width} outputs`);
  }
  return t.data;
}

function linear(op, inputs, attrs, inits, used) {
  const take = (name) => {
    if (!inits.has(name) || used.has(name)) throw new Error(`onnx: ${op} input '${name}' is not an unused initializer`);
    used.add(name);
    return inits.get(name);
  };
  if (op === "MatMul") {
    if (inputs.length !== 2 || Object.keys(attrs).length) throw new Error("onnx: MatMul takes two inputs and no attributes");
    const w = take(inputs[1]);
    if (w.dims.length !== 2) throw new Error("onnx: a MatMul weight must be 2-D");
    return [transpose(w), null];
  }
  const s = { alpha: 1.0, beta: 1.0, transA: 0, transB: 0, ...attrs };
  const keys = Object.keys(s).sort().join(",");
  if (keys !== "alpha,beta,transA,transB" || s.alpha !== 1 || s.beta !== 1 || s.transA !== 0 || ![0, 1].includes(s.transB)) {
    throw new Error(`onnx: Gemm attributes ${JSON.stringify(attrs)} (a decoder's Gemm has alpha = beta = 1, transA = 0)`);
  }
  if (inputs.length !== 2 && inputs.length !== 3) throw new Error("onnx: Gemm takes two or three inputs");
  const w = take(inputs[1]);
  if (w.dims.length !== 2) throw new Error("onnx: a Gemm weight must be 2-D");
  const weight = s.transB ? { rows: w.dims[0], cols: w.dims[1], data: w.data } : transpose(w);
  let b = null;
  if (inputs.length === 3 && inputs[2] !== "") b = bias(take(inputs[2]), weight.rows);
  return [weight, b];
}

/** The decoder graph `bytes` as an MLP description; throws saying why when it is not a valid decoder. */
export function readMlp(bytes) {
  const model = message(bytes, "model");
  for (const raw of model.opset_import || []) message(raw, "opset");
  if (!model.graph) throw new Error("onnx: the model has no graph");
  const graph = message(model.graph[0], "graph");
  const inits = new Map();
  for (const raw of graph.initializer || []) {
    const [name, t] = tensor(raw);
    if (inits.has(name)) throw new Error(`onnx: initializer '${name}' is repeated`);
    inits.set(name, t);
  }
  const inputs = (graph.input || []).map((v) => text(message(v, "value_info"), "name")).filter((n) => !inits.has(n));
  const outputs = (graph.output || []).map((v) => text(message(v, "value_info"), "name"));
  for (const v of graph.value_info || []) message(v, "value_info");
  if (inputs.length !== 1 || outputs.length !== 1) {
    throw new Error(`onnx: the graph must have one input and one output, has ${inputs.length} and ${outputs.length}`);
  }
  const weights = [], biases = [], used = new Set();
  let cur = inputs[0], expect = "linear";
  for (const raw of graph.node || []) {
    const node = message(raw, "node");
    const op = text(node, "op_type"), domain = text(node, "domain");
    const nodeInputs = (node.input || []).map((v) => utf8.decode(v));
    const nodeOutputs = (node.output || []).map((v) => utf8.decode(v));
    const attrs = attributes(node);
    if (domain !== "" && domain !== "ai.onnx") {
      throw new Error(`onnx: node '${op}' of domain '${domain}' (a decoder uses the standard ops only)`);
    }
    if (nodeOutputs.length !== 1 || !nodeOutputs[0] || inits.has(nodeOutputs[0]) || nodeOutputs[0] === inputs[0]) {
      throw new Error(`onnx: node '${op}' must have one new output`);
    }
    const noAttrs = Object.keys(attrs).length === 0;
    if ((op === "MatMul" || op === "Gemm") && expect === "linear") {
      if (nodeInputs[0] !== cur) throw new Error(`onnx: ${op} does not take the previous layer's output`);
      const [w, b] = linear(op, nodeInputs, attrs, inits, used);
      weights.push(w);
      biases.push(b);
      expect = "after linear";
    } else if (op === "Add" && expect === "after linear" && biases[biases.length - 1] === null && noAttrs) {
      if (nodeInputs.length !== 2 || !nodeInputs.includes(cur)) throw new Error("onnx: Add must add a bias to the previous layer's output");
      const name = nodeInputs[0] === cur ? nodeInputs[1] : nodeInputs[0];
      if (!inits.has(name) || used.has(name)) throw new Error(`onnx: Add input '${name}' is not an unused initializer`);
      used.add(name);
      biases[biases.length - 1] = bias(inits.get(name), weights[weights.length - 1].rows);
      expect = "after add";
    } else if (op === "Relu" && (expect === "after linear" || expect === "after add") && noAttrs) {
      if (nodeInputs.length !== 1 || nodeInputs[0] !== cur) throw new Error("onnx: Relu does not take the previous layer's output");
      expect = "linear";
    } else {
      throw new Error(`onnx: node '${op}' is not allowed here (a decoder is MatMul or Gemm layers, each with an `
        + "optional bias Add, with Relu between them)");
    }
    cur = nodeOutputs[0];
  }
  if (!weights.length || expect === "linear" || cur !== outputs[0]) {
    throw new Error("onnx: the graph does not end with a layer that writes its output");
  }
  const unused = [...inits.keys()].filter((n) => !used.has(n)).sort();
  if (unused.length) throw new Error(`onnx: initializers [${unused.map((n) => `'${n}'`).join(", ")}] are not used`);
  if (weights.length > MAX_LAYERS) throw new Error(`onnx: ${weights.length} layers, a decoder has at most ${MAX_LAYERS}`);
  for (let k = 1; k < weights.length; k++) {
    if (weights[k].cols !== weights[k - 1].rows) {
      throw new Error(`onnx: layer ${k} takes ${weights[k].cols} inputs, layer ${k - 1} gives ${weights[k - 1].rows}`);
    }
  }
  return { weights, biases, inputWidth: weights[0].cols, outputWidth: weights[weights.length - 1].rows };
}
