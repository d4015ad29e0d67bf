// The depth sort, off the main thread (a module worker). For one segment, time and camera it evaluates
// every Gaussian's centre and temporal opacity at that time (formats/stg-v1.md, section 2), drops those
// whose opacity is below 1/255 or whose camera-space depth is at or before the near plane (0.01), and
// sorts the rest by increasing depth, ties by index (a stable radix sort on the float32 depth's bits).
//
// Messages in:  {type: "segment", key, count, positionDegree, opacity, t_center, t_scale, position},
//               {type: "forget", key}, {type: "forget-all"}
//               {type: "sort", id, key, tau, R: [9, row-major world-to-camera rotation], t: [3]}
// Messages out: {id, key, order: Uint32Array (Gaussian indices, nearest first), sortMs}

const segments = new Map();
let keys = new Uint32Array(0), index = new Uint32Array(0), tmpKeys = new Uint32Array(0), tmpIndex = new Uint32Array(0);
const counts = new Uint32Array(65536);
const f32 = new Float32Array(1), u32 = new Uint32Array(f32.buffer);

function grow(n) {
  if (keys.length >= n) return;
  keys = new Uint32Array(n); index = new Uint32Array(n); tmpKeys = new Uint32Array(n); tmpIndex = new Uint32Array(n);
}

function pass(srcK, srcI, dstK, dstI, n, shift) {  // one stable counting-sort pass on 16 bits
  counts.fill(0);
  for (let i = 0; i < n; i++) counts[(srcK[i] >>> shift) & 0xffff]++;
  let sum = 0;
  for (let b = 0; b < 65536; b++) { const c = counts[b]; counts[b] = sum; sum += c; }
  for (let i = 0; i < n; i++) {
    const at = counts[(srcK[i] >>> shift) & 0xffff]++;
    dstK[at] = srcK[i];
    dstI[at] = srcI[i];
  }
}

function sort(s, tau, R, t) {
  grow(s.count);
  const P = s.positionDegree + 1, pos = s.position, minOpacity = 1 / 255;
  let n = 0;
  for (let i = 0; i < s.count; i++) {
    const d = tau - s.t_center[i];
    if (!(s.opacity[i] * Math.exp(-s.t_scale[i] * d * d) >= minOpacity)) continue;
    const base = 3 * P * i;
    let x = 0, y = 0, z = 0;
    for (let k = P - 1; k >= 0; k--) {
      x = x * d + pos[base + 3 * k]; y = y * d + pos[base + 3 * k + 1]; z = z * d + pos[base + 3 * k + 2];
    }
    const depth = R[6] * x + R[7] * y + R[8] * z + t[2];
    if (!(depth > 0.01)) continue;
    f32[0] = depth;
    keys[n] = u32[0];  // positive floats order as their bits
    index[n++] = i;
  }
  pass(keys, index, tmpKeys, tmpIndex, n, 0);
  pass(tmpKeys, tmpIndex, keys, index, n, 16);
  return index.slice(0, n);
}

self.onmessage = (event) => {
  const m = event.data;
  if (m.type === "segment") {
    segments.set(m.key, m);
    return;
  }
  if (m.type === "forget") {
    segments.delete(m.key);
    return;
  }
  if (m.type === "forget-all") {
    segments.clear();
    return;
  }
  const s = segments.get(m.key);
  const start = performance.now();
  const order = s ? sort(s, m.tau, m.R, m.t) : new Uint32Array(0);  // (a forgotten segment: nothing to draw)
  self.postMessage({ id: m.id, key: m.key, order, sortMs: performance.now() - start }, [order.buffer]);
};
