// GLSL ES 3.00 sources of the web player, generated per segment layout (formats/stg-v1.md, sections 2-3).
//
// splatShaders(kind, layout) -> {points, project, quad}: per Gaussian (in the sorted order the worker
//   made) time evaluation on the GPU (temporal opacity, position and rotation polynomials, the full
//   model's time features, the sh colour for the view), the EWA footprint of section 3 (near plane,
//   Jacobian clamp or fisheye Jacobian, blur, 3-sigma radius), and the per-pixel alpha of section 3
//   written premultiplied into float render targets (3 channels + alpha per target; 3 targets for the
//   9 features of a full model). Blending is front to back: ONE_MINUS_DST_ALPHA, ONE. `points`: one
//   pass, one point sprite per Gaussian, projected by its vertex shader (where the image fits the
//   largest point size); else `project` writes one record per Gaussian (transform feedback) and
//   `quad` draws one quad per record.
// colourShaders(kind, mlp) -> {vertex, fragment}: one pass over the image: lite and sh clamp the splatted
//   colour; full runs the decoder MLP per pixel on [F[3:9], camera centre, the pixel centre's world ray].
// crossfadeShaders() -> {vertex, fragment}: inside a crossfade (1.3), (1 - w) A + w B of the two
//   segments' rgb, each rendered by the colour pass into a float texture.
//
// Image coordinates: the splat targets are laid out so that gl_FragCoord.xy is the image point
// (u + 0.5, v + 0.5) of pixel (column u, row v): row 0 is the framebuffer's first row, so readPixels
// returns the top row first. The canvas pass flips rows.

export const DATA_WIDTH = 4096;  // texels per row of the Gaussian data texture
export const WEIGHTS_WIDTH = 4096;
export const RECORD_WIDTH = 4096;  // texels per row of the records texture

/** Float offsets of a Gaussian's values in its texels: opacity, t_center, t_scale, scale (3), position
 * ((P+1) x 3), rotation ((Q+1) x 4), features (C); texels = ceil(floats / 4). */
export function dataLayout(positionDegree, rotationDegree, channels) {
  const position = 6, rotation = position + 3 * (positionDegree + 1), features = rotation + 4 * (rotationDegree + 1);
  const floats = features + channels;
  return { positionDegree, rotationDegree, channels, position, rotation, features, floats, texels: Math.ceil(floats / 4) };
}

const f = (j) => `d${j >> 2}.${"xyzw"[j & 3]}`;
const num = (x) => (Number.isInteger(x) ? `${x}.0` : `${x}`);

const CAMERA_UNIFORMS = `
uniform vec3 u_R0, u_R1, u_R2;   // world-to-camera rotation, rows
uniform vec3 u_t;                // world-to-camera translation
uniform vec4 u_intr;             // fx, fy, cx, cy (pixels)
uniform vec2 u_size;             // width, height (pixels)
uniform vec4 u_lim;              // pinhole Jacobian clamp of x/z (min, max) and y/z (min, max)
uniform int u_fisheye;
uniform vec4 u_k;                // fisheye k1..k4
uniform float u_maxAngle;
uniform vec3 u_center;           // camera centre, world
`;

function horner(base, degree, stride, axis) {
  let s = f(base + degree * stride + axis);
  for (let k = degree - 1; k >= 0; k--) s = `(${s}) * dt + ${f(base + k * stride + axis)}`;
  return s;
}

function shColour(L) {
  const degree = { 3: 0, 12: 1, 27: 2, 48: 3 }[L.channels];
  const a = (k, c) => f(L.features + 3 * k + c);
  const terms = [[0, "0.28209479177387814"]];
  if (degree >= 1) terms.push([1, "-0.4886025119029199 * vy"], [2, "0.4886025119029199 * vz"], [3, "-0.4886025119029199 * vx"]);
  if (degree >= 2) {
    terms.push([4, "1.0925484305920792 * vx * vy"], [5, "-1.0925484305920792 * vy * vz"],
      [6, "0.31539156525252005 * (2.0 * vzz - vxx - vyy)"], [7, "-1.0925484305920792 * vx * vz"], [8, "0.5462742152960396 * (vxx - vyy)"]);
  }
  if (degree >= 3) {
    terms.push([9, "-0.5900435899266435 * vy * (3.0 * vxx - vyy)"], [10, "2.890611442640554 * vx * vy * vz"],
      [11, "-0.4570457994644658 * vy * (4.0 * vzz - vxx - vyy)"], [12, "0.3731763325901154 * vz * (2.0 * vzz - 3.0 * vxx - 3.0 * vyy)"],
      [13, "-0.4570457994644658 * vx * (4.0 * vzz - vxx - vyy)"], [14, "1.445305721320277 * vz * (vxx - vyy)"],
      [15, "-0.5900435899266435 * vx * (vxx - 3.0 * vyy)"]);
  }
  const sum = (c) => terms.map(([k, y]) => `(${y}) * ${a(k, c)}`).join(" + ");
  return `
  vec3 dir = mean - u_center;
  float dn = length(dir);
  dir = dn > 0.0 ? dir / dn : vec3(0.0);
  float vx = dir.x, vy = dir.y, vz = dir.z, vxx = vx * vx, vyy = vy * vy, vzz = vz * vz;
  v_f0 = max(vec3(${sum(0)}, ${sum(1)}, ${sum(2)}) + 0.5, 0.0);`;
}

// What the point sprites' vertex shader hands the fragment shader (the quads' names, with a "_" after
// the features, which the projection already names).
const FLAT_OUT = `flat out vec2 v_mu;
flat out vec3 v_conic;
flat out float v_opacity;
flat out vec2 v_half;
flat out vec3 v_f0_;
flat out vec3 v_f1_;
flat out vec3 v_f2_;`;

/** The splatting programs for segments of this layout and model kind. */
export function splatShaders(kind, L) {
  const full = kind === "full";
  const features = kind === "sh" ? shColour(L) : `
  v_f0 = vec3(${f(L.features)}, ${f(L.features + 1)}, ${f(L.features + 2)});${full ? `
  v_f1 = vec3(${f(L.features + 3)}, ${f(L.features + 4)}, ${f(L.features + 5)});
  v_f2 = dt * vec3(${f(L.features + 6)}, ${f(L.features + 7)}, ${f(L.features + 8)});` : ""}`;
  // The projection, as a transform-feedback pass writing one record per Gaussian ("feedback": the
  // quads read them), or as the vertex shader of one point sprite per Gaussian ("points").
  const projection = (mode) => {
    const out = mode === "feedback" ? "out" : "";  // the record's fields: outputs, or the point's locals
    return `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D u_data;
uniform float u_tau;
${CAMERA_UNIFORMS}
in uint a_index;
${out} vec4 g_shape;   // 2D mean (pixels), half extents of the footprint (pixels)
${out} vec4 g_conic;   // conic (power = a dx^2 + b dx dy + c dy^2), temporal opacity (0: culled)
${out} vec4 g_quad;    // the quad drawn: its first axis (unit) and half lengths along both axes (pixels)
${out} vec4 g_f0;      // features 0..2 (w unused)${full ? `
${out} vec4 g_f1;
${out} vec4 g_f2;` : ""}${mode === "points" ? `
${FLAT_OUT}` : ""}
const int T = ${L.texels};
void cull() {
  g_shape = vec4(0.0); g_conic = vec4(0.0); g_quad = vec4(0.0); g_f0 = vec4(0.0);${full ? " g_f1 = vec4(0.0); g_f2 = vec4(0.0);" : ""}${mode === "points" ? `
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // outside the clip volume: not drawn
  gl_PointSize = 1.0;` : ""}
}
void main() {
  vec3 v_f0, v_f1, v_f2;
  int base = int(a_index) * T;
${Array.from({ length: L.texels }, (_, k) => `  vec4 d${k} = texelFetch(u_data, ivec2((base + ${k}) % ${DATA_WIDTH}, (base + ${k}) / ${DATA_WIDTH}), 0);`).join("\n")}
  float dt = u_tau - ${f(1)};
  float o = ${f(0)} * exp(-${f(2)} * dt * dt);
  vec3 mean = vec3(${[0, 1, 2].map((a) => horner(L.position, L.positionDegree, 3, a)).join(", ")});
  vec4 q = vec4(${[0, 1, 2, 3].map((a) => horner(L.rotation, L.rotationDegree, 4, a)).join(", ")});
  float x = dot(u_R0, mean) + u_t.x, y = dot(u_R1, mean) + u_t.y, z = dot(u_R2, mean) + u_t.z;
  if (!(z > 0.01) || !(o >= 1.0 / 255.0)) { cull(); return; }
  float qn = length(q);
  q = qn > 0.0 ? q / qn : vec4(1.0, 0.0, 0.0, 0.0);
  float qw = q.x, qx = q.y, qy = q.z, qz = q.w;
  mat3 rot = mat3(  // columns: the Gaussian's local axes in world space
    1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy + qw * qz), 2.0 * (qx * qz - qw * qy),
    2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx),
    2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
  float fx = u_intr.x, fy = u_intr.y;
  vec3 J0, J1;
  vec2 mu;
  float iz = 1.0 / z;
  if (u_fisheye == 0) {
    float xz = clamp(x * iz, u_lim.x, u_lim.y), yz = clamp(y * iz, u_lim.z, u_lim.w);
    J0 = vec3(fx * iz, 0.0, -fx * iz * xz);
    J1 = vec3(0.0, fy * iz, -fy * iz * yz);
    mu = vec2(fx * x * iz, fy * y * iz) + u_intr.zw;
  } else {
    float r2 = x * x + y * y, r = sqrt(r2);
    float theta = atan(r, z);
    if (!(theta < u_maxAngle)) { cull(); return; }
    float t2 = theta * theta;
    float thetaD = theta * (1.0 + t2 * (u_k.x + t2 * (u_k.y + t2 * (u_k.z + t2 * u_k.w))));
    float slope = 1.0 + t2 * (3.0 * u_k.x + t2 * (5.0 * u_k.y + t2 * (7.0 * u_k.z + t2 * 9.0 * u_k.w)));
    float rho2 = r2 + z * z, radial, ar;
    if (r > 1e-7 * z) { radial = thetaD / r; ar = (slope * z / rho2 - radial) / r2; }
    else { radial = iz; ar = (2.0 * u_k.x - 2.0 / 3.0) * iz * iz * iz; }
    J0 = vec3(fx * (radial + x * x * ar), fx * x * y * ar, -fx * x * slope / rho2);
    J1 = vec3(fy * x * y * ar, fy * (radial + y * y * ar), -fy * y * slope / rho2);
    mu = vec2(fx * x * radial, fy * y * radial) + u_intr.zw;
  }
  vec3 s = vec3(${f(3)}, ${f(4)}, ${f(5)});
  float a = 0.3, b = 0.0, c = 0.3;
  for (int k = 0; k < 3; k++) {
    vec3 g = rot[k] * s[k];
    vec3 m = vec3(dot(u_R0, g), dot(u_R1, g), dot(u_R2, g));
    float t0 = dot(J0, m), t1 = dot(J1, m);
    a += t0 * t0; b += t0 * t1; c += t1 * t1;
  }
  float det = a * c - b * b;
  if (!(det > 0.0)) { cull(); return; }
  float mid = 0.5 * (a + c);
  float radius = ceil(3.0 * sqrt(mid + sqrt(max(0.1, mid * mid - det))));
  float thr = log(255.0 * o) + 0.01;  // beyond the ellipse power = thr, alpha < 1/255
  vec2 h = min(vec2(radius), sqrt(2.0 * thr * vec2(a, c)));
  ${features}
  g_shape = vec4(mu, h);
  g_conic = vec4(vec3(0.5 * c, -b, 0.5 * a) / det, o);
  // The quad: the footprint's box, or where smaller the rectangle along the ellipse's axes that holds
  // power <= thr (both hold every pixel that can pass; the fragment shader tests the box).
  float disc = sqrt(max(0.0, mid * mid - det));
  vec2 e = sqrt(2.0 * thr * vec2(mid + disc, det / (mid + disc)));  // (the smaller eigenvalue, without cancellation)
  vec2 axis = abs(b) > 1e-9 * mid ? normalize(vec2(b, mid + disc - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  g_quad = e.x * e.y < h.x * h.y ? vec4(axis, e) : vec4(1.0, 0.0, h);
  g_f0 = vec4(v_f0, 0.0);${full ? `
  g_f1 = vec4(v_f1, 0.0);
  g_f2 = vec4(v_f2, 0.0);` : ""}${mode === "points" ? `
  // The point sprite: a square holding the part of the footprint's box inside the image (a point whose
  // centre lies outside the clip volume is not drawn, so the centre is that part's), 1 pixel wider
  // than it: every pixel centre of the box lies inside, half a pixel from the edge at least. The
  // fragment shader tests the box.
  vec2 lo = max(mu - h, vec2(0.0)), hi = min(mu + h, u_size);
  if (!(lo.x <= hi.x && lo.y <= hi.y)) { cull(); return; }
  gl_PointSize = max(hi.x - lo.x, hi.y - lo.y) + 1.0;
  gl_Position = vec4((lo + hi) / u_size - 1.0, 0.0, 1.0);
  v_mu = mu;
  v_half = h;
  v_conic = g_conic.xyz;
  v_opacity = o;
  v_f0_ = v_f0;${full ? `
  v_f1_ = v_f1;
  v_f2_ = v_f2;` : ""}` : ""}
}`;
  };
  const project = projection("feedback");
  const R = full ? 6 : 4;  // texels per record: shape, conic, quad, features
  const vertex = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform vec2 u_size;
uniform sampler2D u_records;  // the projection pass's records, nearest first
flat out vec2 v_mu;
flat out vec3 v_conic;
flat out float v_opacity;
flat out vec2 v_half;
flat out vec3 v_f0;
flat out vec3 v_f1;
flat out vec3 v_f2;
vec4 record(int j) { return texelFetch(u_records, ivec2(j % ${RECORD_WIDTH}, j / ${RECORD_WIDTH}), 0); }
void main() {  // a quad per Gaussian, not instanced (instancing is slow in software GL)
  int i = gl_VertexID / 4, v = gl_VertexID % 4, base = i * ${R};  // 4 corners, indexed as 2 triangles
  vec4 shape = record(base), conic = record(base + 1);
  if (conic.w == 0.0) { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); return; }
  v_mu = shape.xy;
  v_half = shape.zw;
  v_conic = conic.xyz;
  v_opacity = conic.w;
  vec4 quad = record(base + 2);
  v_f0 = record(base + 3).xyz;${full ? `
  v_f1 = record(base + 4).xyz;
  v_f2 = record(base + 5).xyz;` : ""}
  // The quad, 1/8 pixel wider on each side than what it must hold: the rasterizer moves its corners
  // to its subpixel grid (WebGL2 allows grids as coarse as 1/16 pixel: SwiftShader's), so with less a
  // pixel centre just inside the footprint's box, as where the box is the radius, could be left out.
  vec2 corner = vec2(float(v & 1), float(v >> 1)) * 2.0 - 1.0;
  vec2 p = shape.xy + (corner.x * (quad.z + 0.125)) * quad.xy + (corner.y * (quad.w + 0.125)) * vec2(-quad.y, quad.x);
  gl_Position = vec4(p / u_size * 2.0 - 1.0, 0.0, 1.0);
}`;
  const fragment = `#version 300 es
precision highp float;
flat in vec2 v_mu;
flat in vec3 v_conic;
flat in float v_opacity;
flat in vec2 v_half;
flat in vec3 v_f0;
flat in vec3 v_f1;
flat in vec3 v_f2;
layout(location = 0) out vec4 o0;${full ? `
layout(location = 1) out vec4 o1;
layout(location = 2) out vec4 o2;` : ""}
void main() {
  vec2 d = gl_FragCoord.xy - v_mu;
  if (abs(d.x) > v_half.x || abs(d.y) > v_half.y) discard;
  float power = v_conic.x * d.x * d.x + v_conic.y * d.x * d.y + v_conic.z * d.y * d.y;
  if (power < 0.0) discard;
  float alpha = min(0.99, v_opacity * exp(-power));
  if (alpha < 1.0 / 255.0) discard;
  o0 = vec4(v_f0 * alpha, alpha);${full ? `
  o1 = vec4(v_f1 * alpha, alpha);
  o2 = vec4(v_f2 * alpha, alpha);` : ""}
}`;
  const varyings = ["g_shape", "g_conic", "g_quad", "g_f0", ...(full ? ["g_f1", "g_f2"] : [])];
  return { project: { vertex: project, fragment: DISCARD_FRAGMENT, varyings }, quad: { vertex, fragment }, recordTexels: R,
    points: { vertex: projection("points"), fragment: fragment.replace(/v_f([012])\b/g, "v_f$1_") } };
}

const DISCARD_FRAGMENT = `#version 300 es
precision highp float;
out vec4 colour;
void main() { colour = vec4(0.0); }`;

export const FULLSCREEN_VERTEX = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;
  gl_Position = vec4(p, 0.0, 1.0);
}`;

/** The decoder as straight-line code with its weights as constants (small decoders, such as the
 * reference 12 -> 6 -> 3: the compiler sees every multiply; software GL runs it several times faster
 * than loops over a weights texture). */
function inlineMlpCode(mlp) {
  const lit = (v) => { const t = Math.fround(v).toPrecision(9); return t.includes("e") || t.includes(".") ? t : `${t}.0`; };
  let inputs = Array.from({ length: mlp.inputWidth }, (_, i) => `x[${i}]`), code = "";
  mlp.weights.forEach((w, k) => {
    const last = k === mlp.weights.length - 1, b = mlp.biases[k], names = [];
    for (let o = 0; o < w.rows; o++) {
      const terms = [b ? lit(b[o]) : "0.0"];
      for (let i = 0; i < w.cols; i++) if (w.data[o * w.cols + i] !== 0) terms.push(`${lit(w.data[o * w.cols + i])} * ${inputs[i]}`);
      const sum = terms.join(" + ").replace(/\+ -/g, "- ");
      code += `  float l${k}_${o} = ${last ? sum : `max(${sum}, 0.0)`};\n`;
      names.push(`l${k}_${o}`);
    }
    inputs = names;
  });
  return `${code}  vec3 y = vec3(${inputs.join(", ")});\n`;
}

export const INLINE_WEIGHTS = 4096;  // decoders with at most this many weights are compiled in

function mlpCode(mlp) {
  if (mlpWeights(mlp).length <= INLINE_WEIGHTS) return inlineMlpCode(mlp);
  // The decoder's layers as loops over the weights texture; x (C + 3 inputs) -> y (3).
  const width = Math.max(...mlp.weights.map((w) => Math.max(w.rows, w.cols)));
  let code = `  float h[${width}];\n  float g[${width}];\n  for (int i = 0; i < ${mlp.inputWidth}; i++) h[i] = x[i];\n`;
  let offset = 0;
  mlp.weights.forEach((w, k) => {
    const last = k === mlp.weights.length - 1, b = mlp.biases[k];
    const bias = b ? `W(${offset + w.rows * w.cols} + o)` : "0.0";
    code += `  for (int o = 0; o < ${w.rows}; o++) {
    float s = ${bias};
    for (int i = 0; i < ${w.cols}; i++) s += W(${offset} + o * ${w.cols} + i) * h[i];
    g[o] = ${last ? "s" : "max(s, 0.0)"};
  }
  for (int o = 0; o < ${w.rows}; o++) h[o] = g[o];\n`;
    offset += w.rows * w.cols + (b ? w.rows : 0);
  });
  return code + "  vec3 y = vec3(h[0], h[1], h[2]);\n";
}

/** The flat float list of the decoder's layers as mlpCode reads it: per layer W (out x in, row-major), b. */
export function mlpWeights(mlp) {
  const parts = [];
  mlp.weights.forEach((w, k) => { parts.push(w.data); if (mlp.biases[k]) parts.push(mlp.biases[k]); });
  const out = new Float32Array(parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) { out.set(p, at); at += p.length; }
  return out;
}

/** The colour pass: splatted features -> rgb in [0, 1] (alpha 1). */
export function colourShaders(kind, mlp, activation) {
  const full = kind === "full";
  const act = { sigmoid: "1.0 / (1.0 + exp(-v))", clamp: "v", identity: "v" }[activation || "clamp"];
  const fragment = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D u_f0;${full ? `
uniform sampler2D u_f1;
uniform sampler2D u_f2;
uniform sampler2D u_weights;` : ""}
uniform int u_flip;  // 1: the canvas (rows top down on screen)
${CAMERA_UNIFORMS}
out vec4 colour;
${full ? `float W(int j) { return texelFetch(u_weights, ivec2(j % ${WEIGHTS_WIDTH}, j / ${WEIGHTS_WIDTH}), 0).x; }
vec3 worldRay(vec2 p) {  // the unit world-space ray through image point p (formats/stg-v1.md, section 1)
  vec2 m = (p - u_intr.zw) / u_intr.xy;
  vec3 dc;
  if (u_fisheye == 0) {
    dc = normalize(vec3(m, 1.0));
  } else {
    float thetaD = length(m);
    float theta = min(thetaD, u_maxAngle);
    for (int i = 0; i < 10; i++) {
      float t2 = theta * theta;
      float slope = 1.0 + t2 * (3.0 * u_k.x + t2 * (5.0 * u_k.y + t2 * (7.0 * u_k.z + t2 * 9.0 * u_k.w)));
      if (slope > 0.0) theta -= (theta * (1.0 + t2 * (u_k.x + t2 * (u_k.y + t2 * (u_k.z + t2 * u_k.w)))) - thetaD) / slope;
      theta = clamp(theta, 0.0, u_maxAngle);
    }
    float sn = thetaD > 0.0 ? sin(theta) / thetaD : 1.0;
    dc = vec3(m * sn, cos(theta));
  }
  return u_R0 * dc.x + u_R1 * dc.y + u_R2 * dc.z;  // R^T dc
}` : ""}
void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  if (u_flip == 1) px.y = int(u_size.y) - 1 - px.y;
  vec4 a = texelFetch(u_f0, px, 0);
${full ? `  vec4 b = texelFetch(u_f1, px, 0), c = texelFetch(u_f2, px, 0);
  vec3 ray = worldRay(vec2(px) + 0.5);
  float x[${mlp.inputWidth}];
  x[0] = b.x; x[1] = b.y; x[2] = b.z; x[3] = c.x; x[4] = c.y; x[5] = c.z;
  x[6] = u_center.x; x[7] = u_center.y; x[8] = u_center.z; x[9] = ray.x; x[10] = ray.y; x[11] = ray.z;
${mlpCode(mlp)}  vec3 v = a.xyz + y;
  colour = vec4(clamp(${act}, 0.0, 1.0), 1.0);` : "  colour = vec4(clamp(a.xyz, 0.0, 1.0), 1.0);"}
}`;
  return { vertex: FULLSCREEN_VERTEX, fragment };
}

/** The crossfade pass (formats/stg-v1.md 1.3): two segments' rgb (float textures, rows as the splat
 * targets) -> (1 - w) A + w B, rows flipped for the canvas. */
export function crossfadeShaders() {
  const fragment = `#version 300 es
precision highp float;
precision highp sampler2D;
uniform sampler2D u_a;
uniform sampler2D u_b;
uniform float u_w;       // the later segment's weight
uniform float u_height;  // pixels
uniform int u_flip;      // 1: the canvas (rows top down on screen)
out vec4 colour;
void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  if (u_flip == 1) px.y = int(u_height) - 1 - px.y;
  vec3 a = texelFetch(u_a, px, 0).rgb, b = texelFetch(u_b, px, 0).rgb;
  colour = vec4(clamp((1.0 - u_w) * a + u_w * b, 0.0, 1.0), 1.0);
}`;
  return { vertex: FULLSCREEN_VERTEX, fragment };
}
