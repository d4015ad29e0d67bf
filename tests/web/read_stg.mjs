// node tests/web/read_stg.mjs FILE.stg OUT_DIR: read FILE with the web player's reader and write what it
// read: OUT_DIR/meta.json ({"error": message} for a refused file) and per segment i the float32 arrays
// seg{i}_{attribute}.f32 and the decoder's layers seg{i}_w{k}.f32 / seg{i}_b{k}.f32 (little-endian).
import { readFileSync, writeFileSync, mkdirSync } from "node:fs";
import { basename } from "node:path";
import { readStg } from "../../stg_runtime/web/stg-format.js";

const [file, out] = process.argv.slice(2);
mkdirSync(out, { recursive: true });
const put = (name, array) => writeFileSync(`${out}/${name}`, Buffer.from(array.buffer, array.byteOffset, array.byteLength));
try {
  const model = await readStg(new Uint8Array(readFileSync(file)), basename(file));
  const segments = model.segments.map((s, i) => {
    const d = s.decoded;
    for (const [name, values] of Object.entries(d)) if (values instanceof Float32Array) put(`seg${i}_${name}.f32`, values);
    if (d.decoder) {
      d.decoder.weights.forEach((w, k) => put(`seg${i}_w${k}.f32`, w.data));
      d.decoder.biases.forEach((b, k) => b && put(`seg${i}_b${k}.f32`, b));
    }
    return { start_frame: s.startFrame, num_frames: s.numFrames, count: s.count, channels: s.channels,
      context_frames: s.contextFrames, crossfade_frames: s.crossfadeFrames,
      activation: d.activation, layers: d.decoder ? d.decoder.weights.map((w, k) => [w.rows, w.cols, !!d.decoder.biases[k]]) : null };
  });
  writeFileSync(`${out}/meta.json`, JSON.stringify({ kind: model.kind, fps: model.fps, num_frames: model.numFrames,
    cameras: model.cameras, segments }));
} catch (e) {
  writeFileSync(`${out}/meta.json`, JSON.stringify({ error: e.message, type: e.name }));
}
