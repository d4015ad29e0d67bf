// Read `.stg` files in the browser (and in node), exactly as formats/stg-v1.md section 4 says: the
// JavaScript twin of stg_runtime/format.py, with the same checks, the same Limits and the same messages
// (each starting with the file's name). Nothing is evaluated; every declaration is checked against the
// limits before anything of that size is allocated.
//
//   readStg(bytes: Uint8Array, name, limits?) -> Promise<model>            a whole file
//   readPrefix(bytes) -> {major, minor, headerLength}                       the first 20 bytes
//   parseHeader(headerBytes, fileSize, name, limits?) -> model without arrays (segments not yet decoded)
//   decodeSegment(model, i, section: {length, bytes(offset, length)}) -> Promise<segment arrays>
//   verifyChecksum(bytes) -> Promise<void>                                    SHA-256 of all but the last 32 bytes
//   segmentsAt(model, t) -> [{index, tau, weight}]                           what to show at t (two in a crossfade)
//   acDecode(data, channels, count, bits) -> Uint16Array                      (1.5) an acB blob's symbols, channel-major
//
// A model: {name, kind, fps, numFrames, startFrame, duration, cameras: [camera], bounds, provenance,
// fileSize, segments: [{startFrame, numFrames, count, positionDegree, rotationDegree, channels,
// contextFrames: [before, after], crossfadeFrames (1.3; [0, 0] and 0 when absent), entry,
// decoded: null | {opacity, t_center, t_scale, position, rotation, scale, features (Float32Array, C-order),
// decoder: null | MLP (onnx-mlp.js), activation}}]}. A camera: {name, width, height, fx, fy, cx, cy,
// model: "pinhole" | "fisheye", k: [k1, k2, k3, k4], worldToCamera: [16 numbers, row-major]}.

import { readMlp } from "./onnx-mlp.js";
import { sha256 } from "./sha256.js";

export const MAGIC = [0x89, 0x53, 0x54, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];
export const VERSION = [1, 5];
export const PREFIX_SIZE = 20;
export const MAX_HEADER = 64 * 2 ** 20;
export const KINDS = ["lite", "full", "sh"];
export const ACTIVATIONS = ["sigmoid", "clamp", "identity"];
export const ATTRIBUTES = ["opacity", "t_center", "t_scale", "position", "rotation", "scale", "features"];
export const SH_CHANNELS = [3, 12, 27, 48];
export const MAX_SPAN = 2 ** 24;  // the largest context_frames / crossfade_frames value a reader accepts (1.3)
const BYTES = { f32: 4, f16: 2, u8: 1, u16: 2, "u8-delta": 1, "u16-delta": 2 };  // the plain encodings (and (1.5) acB, acBits)
const CODECS = ["raw", "zlib"];
export const MAX_CODEBOOK = 2 ** 16;  // rows of a "vq" codebook (1.4)
export const MAX_PARTS = 64;  // parts of a "parts" array (1.4)
export const MAX_AC_BITS = 16;  // B of an "acB" / "acB-delta" encoding (1.5)

/** B of a (1.5) arithmetic-coded encoding "acB" or "acB-delta" (B in 1..16, no leading zero), null for
 * any other (format.py ac_bits). */
export function acBits(encoding) {
  const m = /^ac([1-9][0-9]*)(-delta)?$/.exec(encoding);
  if (!m) return null;
  const bits = Number(m[1]);
  return bits <= MAX_AC_BITS ? bits : null;
}

const isPlain = (encoding) => Object.hasOwn(BYTES, encoding) || acBits(encoding) !== null;

/** The reader's defaults, those of stg_runtime.format.Limits (formats/stg-v1.md, "Limits"). */
export const DEFAULT_LIMITS = Object.freeze({
  maxGaussians: 2 ** 24, maxSegments: 4096, maxFrames: 2 ** 24, maxDegree: 8,
  maxExpansion: 64, expansionAllowance: 64 * 2 ** 20, maxImageSide: 16384,
});

/** A file that is not a valid .stg file; the message starts with the file's name. */
export class FormatError extends Error {
  constructor(message) { super(message); this.name = "FormatError"; }
}

function fail(message) { throw new Error(message); }

function named(name, fn) {
  try {
    return fn();
  } catch (e) {
    if (e instanceof FormatError) throw e;
    throw new FormatError(`${name}: ${e.message}`);
  }
}

async function namedAsync(name, fn) {
  try {
    return await fn();
  } catch (e) {
    if (e instanceof FormatError) throw e;
    throw new FormatError(`${name}: ${e.message}`);
  }
}

const typeName = (v) => (v === null ? "NoneType" : Array.isArray(v) ? "list" : typeof v === "object" ? "dict"
  : typeof v === "number" ? (Number.isInteger(v) ? "int" : "float") : typeof v === "string" ? "str" : typeof v);

/** obj[key], which must exist and be an int, a float (any number), a str, a list or a dict. */
function get(obj, key, kind, where) {
  if (!(key in obj)) fail(`${where}: missing field '${key}'`);
  const v = obj[key];
  const ok = { int: Number.isInteger(v), float: typeof v === "number", str: typeof v === "string",
    list: Array.isArray(v), dict: v !== null && typeof v === "object" && !Array.isArray(v) }[kind];
  if (!ok) fail(`${where}: field '${key}' must be of type ${kind}, got ${typeName(v)}`);
  return v;
}

export function readPrefix(bytes) {
  if (bytes.length < PREFIX_SIZE) fail(`truncated: ${bytes.length} bytes, shorter than the ${PREFIX_SIZE}-byte prefix`);
  if (MAGIC.some((b, i) => bytes[i] !== b)) fail("not an STG file (wrong magic bytes)");
  const view = new DataView(bytes.buffer, bytes.byteOffset, PREFIX_SIZE);
  const major = view.getUint16(8, true), minor = view.getUint16(10, true);
  const headerLength = Number(view.getBigUint64(12, true));
  if (major !== VERSION[0]) fail(`unsupported version ${major}.${minor} (this reader reads ${VERSION[0]}.x)`);
  if (headerLength > MAX_HEADER) fail(`header length ${headerLength} exceeds the ${MAX_HEADER}-byte limit`);
  return { major, minor, headerLength };
}

/** SHA-256 check of a whole file (the last 32 bytes are the digest of everything before them). */
export async function verifyChecksum(bytes) {
  const digest = await sha256(bytes.subarray(0, bytes.length - 32));
  const stored = bytes.subarray(bytes.length - 32);
  if (digest.some((b, i) => b !== stored[i])) fail("checksum mismatch: the file is corrupt or truncated");
}

export function attributeShape(name, count, pdeg, qdeg, channels) {
  return { opacity: [count], t_center: [count], t_scale: [count], position: [count, pdeg + 1, 3],
    rotation: [count, qdeg + 1, 4], scale: [count, 3], features: [count, channels] }[name];
}

function featureChannels(spec, kind, where) {
  if (kind === "lite") return 3;
  if (kind === "full") return 9;
  const shape = spec !== null && typeof spec === "object" ? spec.shape : undefined;
  if (!(Array.isArray(shape) && shape.length === 2 && Number.isInteger(shape[1]) && SH_CHANNELS.includes(shape[1]))) {
    fail(`${where}: shape ${JSON.stringify(shape)} is not (count, C) with C one of (3, 12, 27, 48) `
      + "(3 (d+1)^2 SH coefficients, degree d in 0..3)");
  }
  return shape[1];
}

function layout(s, where, kind, limits) {
  if (s === null || typeof s !== "object" || Array.isArray(s)) fail(`${where}: not a JSON object`);
  const [start, frames, count, pdeg, qdeg] = ["start_frame", "num_frames", "count", "position_degree", "rotation_degree"]
    .map((k) => get(s, k, "int", where));
  if (Math.min(start, count, pdeg, qdeg) < 0 || frames <= 0) fail(`${where}: negative count/degree/start_frame or num_frames <= 0`);
  if (count > limits.maxGaussians) {
    fail(`${where}: ${count} Gaussians, more than the reader's limit of ${limits.maxGaussians} (stg_runtime.format.Limits)`);
  }
  if (Math.max(pdeg, qdeg) > limits.maxDegree) {
    fail(`${where}: polynomial degrees ${pdeg}, ${qdeg} beyond the reader's limit of ${limits.maxDegree}`);
  }
  if (start + frames > limits.maxFrames) fail(`${where}: frames up to ${start + frames}, beyond the reader's limit of ${limits.maxFrames}`);
  const attributes = get(s, "attributes", "dict", where);
  for (const name of ATTRIBUTES) if (!(name in attributes)) fail(`${where}: missing attribute '${name}'`);
  const channels = featureChannels(attributes.features, kind, `${where}, attribute 'features'`);
  let extra = 0;  // codebooks' values (1.4)
  for (const name of ATTRIBUTES) {
    extra += plan(attributes[name], attributeShape(name, count, pdeg, qdeg, channels), `${where}, attribute '${name}'`);
  }
  const span = (v) => Number.isInteger(v) && v >= 0 && v <= MAX_SPAN;  // (true, 1.5, "2": not integers)
  const context = "context_frames" in s ? s.context_frames : [0, 0];
  if (!(Array.isArray(context) && context.length === 2 && context.every(span))) {
    fail(`${where}: context_frames must be a list of two integers in [0, ${MAX_SPAN}]`);
  }
  const crossfade = "crossfade_frames" in s ? s.crossfade_frames : 0;
  if (!span(crossfade)) fail(`${where}: crossfade_frames must be an integer in [0, ${MAX_SPAN}]`);
  return { startFrame: start, numFrames: frames, count, positionDegree: pdeg, rotationDegree: qdeg, channels,
    contextFrames: context.slice(), crossfadeFrames: crossfade, extra };
}

function camera(c, limits) {
  if (c === null || typeof c !== "object" || Array.isArray(c)) throw new TypeError("a camera is a JSON object");
  const model = "model" in c ? c.model : "pinhole";
  if (model !== "pinhole" && model !== "fisheye") {
    fail(`ValueError: unknown camera model ${JSON.stringify(model)} (this reader knows pinhole, fisheye)`);
  }
  const w2c = c.world_to_camera;
  if (!Array.isArray(w2c) || w2c.length !== 16 || w2c.some((v) => typeof v !== "number")) {
    fail("ValueError: world_to_camera must be 16 numbers");
  }
  const intr = model === "pinhole" ? c : c.intrinsics;
  if (intr === null || typeof intr !== "object") fail("KeyError: 'intrinsics'");
  for (const key of ["fx", "fy", "cx", "cy", ...(model === "fisheye" ? ["k1", "k2", "k3", "k4"] : [])]) {
    if (!(key in intr)) fail(`KeyError: '${key}'`);
    if (typeof intr[key] !== "number") fail(`TypeError: ${key} must be a number`);
  }
  for (const key of ["width", "height"]) {
    if (!(key in c)) fail(`KeyError: '${key}'`);
    if (typeof c[key] !== "number") fail(`TypeError: ${key} must be a number`);
  }
  const cam = { name: typeof c.name === "string" ? c.name : "", width: Math.trunc(c.width), height: Math.trunc(c.height),
    fx: intr.fx, fy: intr.fy, cx: intr.cx, cy: intr.cy, model,
    k: model === "fisheye" ? [intr.k1, intr.k2, intr.k3, intr.k4] : [0, 0, 0, 0], worldToCamera: w2c.slice() };
  if (!(cam.width > 0 && cam.height > 0)) fail(`ValueError: image size must be positive, got ${cam.width}x${cam.height}`);
  if (!(cam.fx > 0 && cam.fy > 0)) fail(`ValueError: focal lengths must be positive, got fx=${cam.fx}, fy=${cam.fy}`);
  if (!w2c.every(Number.isFinite)) fail("ValueError: world_to_camera has non-finite entries");
  if (!cam.k.every(Number.isFinite)) fail("ValueError: a fisheye camera takes 4 finite distortion coefficients");
  const side = limits.maxImageSide;
  if (cam.width > side || cam.height > side) {
    fail(`ValueError: image size ${cam.width}x${cam.height} exceeds the reader's limit of ${side} pixels`);
  }
  if (!(cam.fx >= 1e-3 && cam.fx <= 1e9 && cam.fy >= 1e-3 && cam.fy <= 1e9)) {
    fail(`ValueError: focal lengths fx=${cam.fx}, fy=${cam.fy} outside [1e-3, 1e9] pixels`);
  }
  if (!(Math.abs(cam.cx) <= 1e9 && Math.abs(cam.cy) <= 1e9)) {
    fail(`ValueError: principal point (${cam.cx}, ${cam.cy}) is not within 1e9 pixels`);
  }
  if (!isRigid(w2c)) fail("ValueError: world_to_camera is not a rigid transform (rotation, translation, last row 0 0 0 1)");
  return cam;
}

function isRigid(m) {
  let worst = 0;
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 3; j++) {
      let dot = 0;
      for (let k = 0; k < 3; k++) dot += m[4 * i + k] * m[4 * j + k];
      worst = Math.max(worst, Math.abs(dot - (i === j ? 1 : 0)));
    }
  }
  const det = m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) + m[2] * (m[4] * m[9] - m[5] * m[8]);
  const t = Math.max(Math.abs(m[3]), Math.abs(m[7]), Math.abs(m[11]));
  return worst <= 1e-4 && det > 0 && m[12] === 0 && m[13] === 0 && m[14] === 0 && m[15] === 1 && t <= 1e12;
}

/** Parse camera `c` (a camera object of formats/stg-v1.md or of a camera-path JSON file); throws Error. */
export function parseCamera(c, limits = DEFAULT_LIMITS) {
  try {
    return camera(c, limits);
  } catch (e) {
    throw new Error(`invalid camera (${e.message})`);
  }
}

/** The header (UTF-8 JSON bytes) of a file of `fileSize` bytes, checked: a model whose segments are
 * not decoded yet. Throws FormatError. */
export function parseHeader(headerBytes, fileSize, name, limits = DEFAULT_LIMITS) {
  return named(name, () => {
    let header;
    try {
      header = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(headerBytes));
    } catch (e) {
      fail(`header is not valid UTF-8 JSON (${e.message})`);
    }
    if (header === null || typeof header !== "object" || Array.isArray(header)) fail("header is not a JSON object");
    const kind = get(header, "kind", "str", "header");
    if (!KINDS.includes(kind)) {
      fail(`header: unknown model kind '${kind}' (this reader, version ${VERSION.join(".")}, renders ${KINDS.join(", ")}; a newer one may read it)`);
    }
    const entries = get(header, "segments", "list", "header");
    if (!entries.length) fail("header: no segments");
    if (entries.length > limits.maxSegments) fail(`header: ${entries.length} segments, more than the reader's limit of ${limits.maxSegments}`);
    const segments = entries.map((s, i) => ({ ...layout(s, `segment ${i}`, kind, limits), entry: s, decoded: null }));
    let values = 0;
    for (const s of segments) {
      for (const a of ATTRIBUTES) values += attributeShape(a, s.count, s.positionDegree, s.rotationDegree, s.channels).reduce((x, y) => x * y, 1);
      values += s.extra;
    }
    const allowed = limits.maxExpansion * fileSize + limits.expansionAllowance;
    if (4 * values > allowed) {
      fail(`the arrays would take ${4 * values} bytes in memory, more than the reader allows for a ${fileSize}-byte file `
        + `(${Math.round(allowed)}; stg_runtime.format.Limits)`);
    }
    const total = segments.reduce((n, s) => n + s.numFrames, 0);
    if (get(header, "num_frames", "int", "header") !== total) fail(`header: num_frames ${header.num_frames} is not the segments' total`);
    segments.forEach((s, i) => {
      if (i && s.startFrame !== segments[i - 1].startFrame + segments[i - 1].numFrames) {
        fail(`model: segment ${i} starts at frame ${s.startFrame}, not right after segment ${i - 1}`);
      }
      const decoder = s.entry.decoder;
      if ((decoder === undefined || decoder === null) !== (kind !== "full")) {
        fail(`model: segment ${i}: a ${kind} model ${kind === "full" ? "needs" : "has no"} decoder`);
      }
    });
    if (segments[0].crossfadeFrames) fail("model: segment 0 has crossfade_frames, but no segment before it to fade from");
    segments.forEach((s, i) => {  // a segment's fade-in and fade-out must not overlap (formats/stg-v1.md, section 2)
      const fadeOut = i + 1 < segments.length ? segments[i + 1].crossfadeFrames : 0;
      if (s.crossfadeFrames + fadeOut > 2 * s.numFrames) {
        fail(`model: segment ${i} (${s.numFrames} frames) is too short for its crossfades `
          + `(${s.crossfadeFrames} in, ${fadeOut} out): half of each must fit in it`);
      }
    });
    const cameras = ("cameras" in header ? get(header, "cameras", "list", "header") : []).map((c, i) => {
      try {
        return camera(c, limits);
      } catch (e) {
        return fail(`camera ${i}: invalid (${e.message})`);
      }
    });
    let bounds = header.bounds === undefined ? null : header.bounds;
    if (bounds !== null) {
      if (typeof bounds !== "object") fail("bounds: min and max must be 3 finite numbers each");
      const lo = get(bounds, "min", "list", "bounds"), hi = get(bounds, "max", "list", "bounds");
      if (lo.length !== 3 || hi.length !== 3 || ![...lo, ...hi].every(Number.isFinite)) fail("bounds: min and max must be 3 finite numbers each");
      bounds = { min: lo, max: hi };
    }
    const provenance = "provenance" in header ? header.provenance : {};
    if (provenance === null || typeof provenance !== "object" || Array.isArray(provenance)) fail("header: provenance must be an object");
    const fps = get(header, "fps", "float", "header");
    if (!(fps >= 1e-3 && fps <= 1e6)) fail(`header: fps ${fps} is outside [0.001, 1000000]`);
    const startFrame = segments[0].startFrame;
    return { name, kind, fps, numFrames: total, startFrame, startTime: startFrame / fps, duration: total / fps, cameras,
      bounds, provenance, fileSize, segments };
  });
}

// -- arrays -------------------------------------------------------------------------------------

const HALF = (() => {  // uint16 bits -> float32, every value
  const out = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 31, m = h & 1023;
    out[h] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return out;
})();

/** Whether the whole of `data` is a zlib stream (any output, discarded) that the platform reads without error. */
async function inflates(data) {
  const reader = new Blob([data]).stream().pipeThrough(new DecompressionStream("deflate")).getReader();
  try {
    for (;;) if ((await reader.read()).done) return true;
  } catch {
    return false;
  }
}

let refusesJunk = null;  // a Promise: whether this platform's DecompressionStream refuses bytes after the stream
function platformRefusesJunk() {  // (Chromium does; node 20 ignores them)
  if (refusesJunk === null) refusesJunk = inflates(new Uint8Array([0x78, 0x9c, 0x03, 0x00, 0, 0, 0, 1, 0])).then((ok) => !ok);
  return refusesJunk;
}

async function inflate(data, size, where) {
  // zlib (RFC 1950) through the platform's DecompressionStream; never more than `size` bytes, and the
  // stream must end exactly at the end of the blob (as Python's zlib checks).
  const junk = `${where}: zlib data does not end after ${size} bytes (longer, cut short or with junk)`;
  const out = new Uint8Array(size);
  let at = 0;
  const reader = new Blob([data]).stream().pipeThrough(new DecompressionStream("deflate")).getReader();
  try {
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      if (at + value.length > size) { reader.cancel().catch(() => {}); fail(junk); }
      out.set(value, at);
      at += value.length;
    }
  } catch (e) {
    if (e.message === junk) throw e;
    fail(junk);
  }
  if (at !== size) fail(`${where}: blob holds ${at} bytes, shape and encoding imply ${size}`);
  // Where the platform ignores bytes after the stream's end: the stream ends at the blob's last byte
  // exactly when the blob without that byte is not a whole stream.
  if (!(await platformRefusesJunk()) && (await inflates(data.subarray(0, data.length - 1)))) fail(junk);
  return out;
}

async function blob(spec, section, size, where) {
  const offset = get(spec, "offset", "int", where), length = get(spec, "length", "int", where);
  const codec = get(spec, "codec", "str", where);
  if (offset < 0 || length < 0 || offset + length > section.length) {
    fail(`${where}: blob [${offset}, ${offset + length}) lies outside the ${section.length}-byte data section`);
  }
  if (!(size !== null ? CODECS : ["raw"]).includes(codec)) fail(`${where}: unsupported codec '${codec}'`);
  const data = section.bytes(offset, length);
  if (codec === "zlib") return inflate(data, size, where);
  if (size !== null && data.length !== size) fail(`${where}: blob holds ${data.length} bytes, shape and encoding imply ${size}`);
  return data;
}

function numbers(list, channels) {
  if (!Array.isArray(list) || list.length !== channels || list.some((v) => typeof v !== "number")) return null;
  return list.map(Math.fround);
}

const isObject = (v) => v !== null && typeof v === "object" && !Array.isArray(v);
const sameShape = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);

/** Check an array entry's structure against `shape` before any of it is decoded (format.py _plan): its
 * shape, its encoding (a plain one: BYTES' or (1.5) acB), (1.4) a "vq" codebook's shape and a "parts"
 * entry's parts. Returns the float32 values its decoding takes beyond the array itself (codebooks).
 * inside: "codebook" or "part". */
function plan(spec, shape, where, inside = "") {
  if (!isObject(spec)) fail(`${where}: not a JSON object`);
  const declared = get(spec, "shape", "list", where);
  if (!sameShape(declared, shape)) {
    fail(`${where}: shape ${JSON.stringify(declared)} disagrees with count and degrees, expected ${JSON.stringify(shape)}`);
  }
  const encoding = get(spec, "encoding", "str", where);
  const channels = shape.slice(1).reduce((a, b) => a * b, 1);
  if (isPlain(encoding)) return 0;
  if (encoding === "vq" && inside !== "codebook") {
    const book = get(spec, "codebook", "dict", where);
    const rows = Array.isArray(book.shape) && book.shape.length ? book.shape[0] : null;
    if (!(Number.isInteger(rows) && rows >= 1 && rows <= MAX_CODEBOOK)) {
      fail(`${where}: a codebook's shape must be [K, ${channels}] with K in [1, ${MAX_CODEBOOK}], `
        + `got ${JSON.stringify(book.shape ?? null)}`);
    }
    plan(book, [rows, channels], `${where}, codebook`, "codebook");
    return rows * channels;
  }
  if (encoding === "parts" && !inside) {
    const parts = get(spec, "parts", "list", where);
    if (!(parts.length >= 1 && parts.length <= MAX_PARTS)) {
      fail(`${where}: ${parts.length} parts, expected 1 to ${MAX_PARTS}`);
    }
    let extra = 0, covered = 0;
    for (let j = 0; j < parts.length; j++) {
      const part = parts[j];
      const width = isObject(part) && Array.isArray(part.shape) && part.shape.length === 2 ? part.shape[1] : null;
      if (!(Number.isInteger(width) && width >= 1)) {
        fail(`${where}, part ${j}: shape must be [${shape[0]}, channels >= 1]`);
      }
      covered += width;
      if (covered > channels) break;
      extra += plan(part, [shape[0], width], `${where}, part ${j}`, "part");
    }
    if (covered !== channels) fail(`${where}: the parts cover ${covered} channels, the array has ${channels}`);
    return extra;
  }
  return fail(`${where}: unknown encoding '${encoding}'${inside ? ` (not allowed in a ${inside})` : ""}`);
}

// -- (1.5) the adaptive binary range coder of "acB" (formats/stg-v1.md, "Arithmetic-coded fixed point";
// stg_runtime/range_coder.py) ------------------------------------------------------------------------

const PROB_BITS = 11;  // probabilities of a 0 in units of 2^-11
const PROB_ONE = 1 << PROB_BITS;
const ADAPT_SHIFT = 5;  // a probability moves 1/32 of the way towards each coded bit
const TOP_SHIFT = 24;  // the range is renormalised (a byte shifted in) while below 2^24
const SIGN = -0x80000000;  // int32 sign bit

/** Decode `channels` x `count` symbols of `bits` bits from the coded bytes `data` (Uint8Array):
 * Uint16Array, channel-major. Throws Error (range_coder.decode's messages) when `data` is not the
 * stream of exactly that many symbols: first byte not 0, ends early, bytes left over.
 * range, code and bound are the spec's unsigned 32-bit integers held as int32 bit patterns: every step
 * is exact modulo 2^32 (bound = (range >>> 11) * p < 2^32 by Math.imul, code - bound and range - bound
 * are taken only where they are >= 0), an unsigned comparison flips both sign bits, and range < 2^24
 * is (range >>> 24) === 0. Twice as fast in V8 as the same steps on doubles kept unsigned by `>>> 0`. */
export function acDecode(data, channels, count, bits) {
  const n = channels * count;
  if (!data.length || data[0] !== 0) fail("arithmetic-coded data must start with a 0 byte");
  const early = `arithmetic-coded data ends before its ${n} values`;
  const size = data.length;
  if (size < 5) fail(early);
  const out = new Uint16Array(n);
  const probs = new Uint16Array(1 << bits);
  const leaf = 1 << bits;
  let range = -1, code = (data[1] << 24) | (data[2] << 16) | (data[3] << 8) | data[4], at = 5;  // 2^32 - 1, bytes 1-4
  for (let c = 0; c < channels; c++) {
    probs.fill(PROB_ONE >> 1);
    for (let i = 0, k = c * count; i < count; i++, k++) {
      let node = 1;
      while (node < leaf) {  // `bits` bits, most significant first, down the tree
        const p = probs[node];
        const bound = Math.imul(range >>> PROB_BITS, p);
        if ((code ^ SIGN) < (bound ^ SIGN)) {  // code < bound, unsigned: a 0
          range = bound;
          probs[node] = p + ((PROB_ONE - p) >> ADAPT_SHIFT);
          node <<= 1;
        } else {
          code = (code - bound) | 0;
          range = (range - bound) | 0;
          probs[node] = p - (p >> ADAPT_SHIFT);
          node = (node << 1) | 1;
        }
        while (range >>> TOP_SHIFT === 0) {  // range < 2^24: a byte in
          if (at >= size) fail(early);
          range <<= 8;
          code = (code << 8) | data[at++];
        }
      }
      out[k] = node - leaf;
    }
  }
  if (at !== size) fail(`arithmetic-coded data has ${size - at} bytes after its ${n} values`);
  return out;
}

/** Values of an "acB" / "acB-delta" entry (1.5), checked in format.py's order: the blob (raw only),
 * the coded stream, then offset and scale. */
async function acValues(spec, count, channels, bits, section, where) {
  const data = await blob(get(spec, "data", "dict", where), section, null, where);
  let symbols;
  try {
    symbols = acDecode(data, channels, count, bits);
  } catch (e) {
    fail(`${where}: ${e.message}`);
  }
  const base = spec.encoding.replace("-delta", "");
  const offset = numbers(spec.offset, channels), scale = numbers(spec.scale, channels);
  if (!offset || !scale) fail(`${where}: ${base} needs lists 'offset' and 'scale' of ${channels} numbers`);
  const out = new Float32Array(count * channels);
  const delta = spec.encoding.endsWith("-delta"), mask = (1 << bits) - 1;
  for (let c = 0; c < channels; c++) {
    const o = offset[c], s = scale[c];
    let q = 0;
    for (let i = 0, k = c * count, j = c; i < count; i++, k++, j += channels) {
      q = delta ? (q + symbols[k]) & mask : symbols[k];  // (-delta: running sums modulo 2^B)
      out[j] = o + s * q;  // float64, then float32
    }
  }
  return out;
}

/** Values of a plain array entry (checked by plan): Float32Array of count x channels, C-order. */
async function plainValues(spec, count, channels, section, where) {
  const encoding = spec.encoding, n = count * channels;
  const bits = acBits(encoding);
  if (bits !== null) return acValues(spec, count, channels, bits, section, where);
  let offset = null, scale = null;
  const base = encoding.replace("-delta", "");
  if (base === "u8" || base === "u16") {  // checked before the blob is decoded
    offset = numbers(spec.offset, channels);
    scale = numbers(spec.scale, channels);
    if (!offset || !scale) fail(`${where}: ${base} needs lists 'offset' and 'scale' of ${channels} numbers`);
  }
  const raw = await blob(get(spec, "data", "dict", where), section, n * BYTES[encoding], where);
  const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
  const out = new Float32Array(n);
  if (encoding === "f32") for (let i = 0; i < n; i++) out[i] = view.getFloat32(4 * i, true);
  else if (encoding === "f16") for (let i = 0; i < n; i++) out[i] = HALF[view.getUint16(2 * i, true)];
  else if (encoding === "u8") for (let i = 0; i < n; i++) out[i] = offset[i % channels] + scale[i % channels] * raw[i];
  else if (encoding === "u16") {
    for (let i = 0; i < n; i++) out[i] = offset[i % channels] + scale[i % channels] * view.getUint16(2 * i, true);
  } else {  // (1.4) channel-major differences modulo 2^bits (u16: a plane of low bytes, then of high): running sums
    const wide = base === "u16", mask = wide ? 0xffff : 0xff;
    for (let c = 0; c < channels; c++) {
      let q = 0;
      for (let i = 0; i < count; i++) {
        const k = c * count + i;
        q = (q + (wide ? raw[k] | (raw[n + k] << 8) : raw[k])) & mask;
        out[i * channels + c] = offset[c] + scale[c] * q;
      }
    }
  }
  return out;
}

/** Values of an array entry (checked by plan) of `count` rows of `channels`: Float32Array, C-order. */
async function values(spec, count, channels, section, where) {
  if (spec.encoding === "parts") {  // (1.4) consecutive channels, each part decoded into its place
    const out = new Float32Array(count * channels);
    let at = 0;
    for (let j = 0; j < spec.parts.length; j++) {
      const width = spec.parts[j].shape[1];
      const part = await values(spec.parts[j], count, width, section, `${where}, part ${j}`);
      for (let i = 0; i < count; i++) out.set(part.subarray(i * width, (i + 1) * width), i * channels + at);
      at += width;
    }
    return out;
  }
  if (spec.encoding === "vq") {  // (1.4) codebook rows picked by an index per value
    const rows = spec.codebook.shape[0];
    const book = await values(spec.codebook, rows, channels, section, `${where}, codebook`);
    const size = rows <= 256 ? 1 : 2;
    const raw = await blob(get(spec, "data", "dict", where), section, count * size, where);
    const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
    const out = new Float32Array(count * channels);
    let worst = -1;
    for (let i = 0; i < count; i++) worst = Math.max(worst, size === 1 ? raw[i] : view.getUint16(2 * i, true));
    if (worst >= rows) fail(`${where}: index ${worst} beyond the codebook's ${rows} rows`);
    for (let i = 0; i < count; i++) {
      const r = size === 1 ? raw[i] : view.getUint16(2 * i, true);
      out.set(book.subarray(r * channels, (r + 1) * channels), i * channels);
    }
    return out;
  }
  return plainValues(spec, count, channels, section, where);
}

async function array(spec, shape, section, where) {
  const count = shape[0], channels = shape.slice(1).reduce((a, b) => a * b, 1);
  const out = await values(spec, count, channels, section, where);
  for (let i = 0; i < out.length; i++) {
    if (!Number.isFinite(out[i])) fail(`${where}: decoded values are not all finite`);
  }
  return out;
}

/** Decode segment i of `model` from its data section ({length, bytes(offset, length) -> Uint8Array});
 * stores and returns segment.decoded. Throws FormatError. */
export async function decodeSegment(model, i, section) {
  const s = model.segments[i];
  if (s.decoded) return s.decoded;
  const where = `segment ${i}`;
  const decoded = await namedAsync(model.name, async () => {
    const out = {};
    for (const name of ATTRIBUTES) {
      const shape = attributeShape(name, s.count, s.positionDegree, s.rotationDegree, s.channels);
      out[name] = await array(s.entry.attributes[name], shape, section, `${where}, attribute '${name}'`);
    }
    out.decoder = null;
    out.activation = "sigmoid";
    const d = s.entry.decoder;
    if (d !== undefined && d !== null) {
      if (typeof d !== "object" || Array.isArray(d)) fail(`${where}: decoder must be an object or null`);
      out.activation = get(d, "activation", "str", `${where}, decoder`);
      if (!ACTIVATIONS.includes(out.activation)) {
        fail(`${where}, decoder: activation must be one of ('sigmoid', 'clamp', 'identity'), got '${out.activation}'`);
      }
      const bytes = await blob(get(d, "data", "dict", `${where}, decoder`), section, null, `${where}, decoder`);
      try {
        out.decoder = readMlp(bytes);
      } catch (e) {
        fail(`${where}, decoder: ${e.message}`);
      }
      const { inputWidth, outputWidth } = out.decoder;
      if (inputWidth !== s.channels + 3 || outputWidth !== 3) {
        fail(`${where}: segment: the decoder maps ${inputWidth} -> ${outputWidth} channels; with ${s.channels} features `
          + `it must map ${s.channels + 3} -> 3`);
      }
    }
    return out;
  });
  s.decoded = decoded;
  return decoded;
}

/** A data section held in memory: `bytes` is the whole file. */
export function fileSection(bytes, headerLength) {
  const start = PREFIX_SIZE + headerLength, length = bytes.length - 32 - start;
  return { length, bytes: (offset, n) => bytes.subarray(start + offset, start + offset + n) };
}

/** Read a whole file: prefix, checksum, header, every segment. Throws FormatError naming `name`. */
export async function readStg(bytes, name = "<bytes>", limits = DEFAULT_LIMITS) {
  const { headerLength } = named(name, () => {
    const prefix = readPrefix(bytes);
    if (bytes.length < PREFIX_SIZE + prefix.headerLength + 32) {
      fail(`truncated: header says ${prefix.headerLength} header bytes, file has ${bytes.length} bytes in all`);
    }
    return prefix;
  });
  await namedAsync(name, () => verifyChecksum(bytes));
  const model = parseHeader(bytes.subarray(PREFIX_SIZE, PREFIX_SIZE + headerLength), bytes.length, name, limits);
  const section = fileSection(bytes, headerLength);
  for (let i = 0; i < model.segments.length; i++) await decodeSegment(model, i, section);
  return model;
}

/** The segment index holding time t (seconds) and its normalised time tau (formats/stg-v1.md, section 2);
 * inside a crossfade, the one whose frames hold t (segmentsAt says what to show). */
export function segmentAt(model, t) {
  const frame = Math.floor(t * model.fps + 1e-9);
  let i = 0;
  while (i < model.segments.length - 1 && frame >= model.segments[i].startFrame + model.segments[i].numFrames) i++;
  return { index: i, tau: tauOf(model, model.segments[i], t) };
}

/** Normalised time of `segment` at t seconds (outside [0, 1] beyond its frames). */
export function tauOf(model, segment, t) {
  return (t - segment.startFrame / model.fps) / (segment.numFrames / model.fps);
}

/** What a player shows at time t (stg_runtime.model.Model.segments_at): [{index, tau, weight}], one entry
 * of weight 1, or two (the earlier segment first) inside a crossfade, whose weights add up to 1; the
 * image is (1 - w) render_A + w render_B. A crossfade of b frames into segment B starting at frame s
 * spans x = t * fps in [s - 1/2 - b/2, s - 1/2 + b/2], w = (x - (s - 1/2 - b/2)) / b (section 2,
 * "Segments and crossfades"). */
export function segmentsAt(model, t) {
  const { index, tau } = segmentAt(model, t);
  const x = t * model.fps, segments = model.segments;
  for (const later of [index, index + 1]) {  // the fade into the segment, and the fade out of it
    if (later > 0 && later < segments.length && segments[later].crossfadeFrames) {
      const b = segments[later].crossfadeFrames;
      const w = (x - (segments[later].startFrame - 0.5 - 0.5 * b)) / b;
      if (w > 0 && w < 1) {
        return [{ index: later - 1, tau: tauOf(model, segments[later - 1], t), weight: 1 - w },
          { index: later, tau: tauOf(model, segments[later], t), weight: w }];
      }
    }
  }
  return [{ index, tau, weight: 1 }];
}
