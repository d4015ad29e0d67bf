// WebGL2 rendering of one segment at one time from one camera (formats/stg-v1.md, sections 2-3): the
// Gaussians' data in a float texture; in the worker's depth order, one point sprite per Gaussian
// (projected by its vertex shader) where the image fits the largest point size, else one record per
// Gaussian (transform feedback) and one quad per record; features splatted front to back into float
// render targets, then the colour pass (shaders.js).
//
//   new Renderer(canvas)                  throws Error with a readable message without WebGL2 or float targets
//   renderer.upload(model, i) -> gpu      segment i's textures and programs (model from stg-format.js)
//   renderer.setOrder(gpu, order)         the instance order (Uint32Array of Gaussian indices, nearest first)
//   renderer.usePoints = false            always the records and quads (tests, benchmarks)
//   renderer.draw(gpu, camera, tau, target) target "canvas" or "pixels" (then returns Uint8Array RGBA,
//                                          top row first, camera.width x camera.height)
//   renderer.drawCrossfade(parts, camera, target)  inside a crossfade (formats/stg-v1.md 1.3): parts =
//                                          [{gpu, tau, weight}] x 2; each segment's rgb into a float
//                                          texture, then (1 - w) A + w B in one pass; returns as draw

import { DATA_WIDTH, RECORD_WIDTH, WEIGHTS_WIDTH, dataLayout, splatShaders, colourShaders, crossfadeShaders,
  mlpWeights } from "./shaders.js";

/** The largest angle off the axis a fisheye sees: the first zero of d theta_d / d theta, or pi. */
export function fisheyeMaxAngle(k) {
  const slope = (t) => { const t2 = t * t; return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3]))); };
  const steps = 4096;
  for (let s = 1; s <= steps; s++) {
    let lo = (Math.PI * (s - 1)) / steps, hi = (Math.PI * s) / steps;
    if (slope(hi) <= 0) {
      for (let it = 0; it < 60; it++) { const m = 0.5 * (lo + hi); if (slope(m) > 0) lo = m; else hi = m; }
      return hi;
    }
  }
  return Math.PI;
}

/** The uniforms every pass takes for `camera` (a camera of stg-format.js). */
export function cameraUniforms(camera) {
  const m = camera.worldToCamera, W = camera.width, H = camera.height;
  const R = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]], t = [m[3], m[7], m[11]];
  const center = [0, 1, 2].map((j) => -(R[j] * t[0] + R[3 + j] * t[1] + R[6 + j] * t[2]));
  const tx = (0.3 * W) / (2 * camera.fx), ty = (0.3 * H) / (2 * camera.fy);
  const fisheye = camera.model === "fisheye";
  return { R, t, center, intr: [camera.fx, camera.fy, camera.cx, camera.cy], size: [W, H],
    lim: [-(camera.cx / camera.fx + tx), (W - camera.cx) / camera.fx + tx, -(camera.cy / camera.fy + ty), (H - camera.cy) / camera.fy + ty],
    fisheye: fisheye ? 1 : 0, k: camera.k, maxAngle: fisheye ? fisheyeMaxAngle(camera.k) : Math.PI / 2 };
}

export class Renderer {
  constructor(canvas) {
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, stencil: false,
      premultipliedAlpha: false, preserveDrawingBuffer: false });
    if (!gl) throw new Error("this browser has no WebGL2: the player needs it (any browser of the last years has it)");
    if (!gl.getExtension("EXT_color_buffer_float")) {
      throw new Error("this browser's WebGL2 cannot render to float textures (EXT_color_buffer_float): the player needs it");
    }
    this.floatBlend = !!gl.getExtension("EXT_float_blend");
    this.featureFormat = this.floatBlend ? gl.RGBA32F : gl.RGBA16F;  // 16-bit floats blend without the extension
    this.gl = gl;
    this.canvas = canvas;
    this.programs = new Map();
    this.targets = null;
    this.maxTexture = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    this.maxPointSize = gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1];
    this.usePoints = true;  // point sprites where the image fits them (false: always the records and quads)
  }

  /** Whether a point sprite can hold any footprint's part inside a W x H image (see shaders.js). */
  pointsFit(W, H) {
    return this.usePoints && Math.max(W, H) + 1 <= this.maxPointSize;
  }

  program(key, sources) {
    if (this.programs.has(key)) return this.programs.get(key);
    const gl = this.gl;
    const compile = (type, source) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, source);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
      return s;
    };
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, sources.vertex));
    gl.attachShader(p, compile(gl.FRAGMENT_SHADER, sources.fragment));
    (sources.attributes || []).forEach((name, k) => gl.bindAttribLocation(p, k, name));
    if (sources.varyings) gl.transformFeedbackVaryings(p, sources.varyings, gl.INTERLEAVED_ATTRIBS);
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`shader link: ${gl.getProgramInfoLog(p)}`);
    const uniforms = {};
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
      const name = gl.getActiveUniform(p, i).name;
      uniforms[name] = gl.getUniformLocation(p, name);
    }
    const entry = { program: p, uniforms };
    this.programs.set(key, entry);
    return entry;
  }

  floatTexture(format, width, height, data) {
    const gl = this.gl, tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    const fmt = { [gl.RGBA32F]: [gl.RGBA, gl.FLOAT], [gl.R32F]: [gl.RED, gl.FLOAT], [gl.RGBA16F]: [gl.RGBA, gl.HALF_FLOAT],
      [gl.RGBA8]: [gl.RGBA, gl.UNSIGNED_BYTE] }[format];
    gl.texImage2D(gl.TEXTURE_2D, 0, format, width, height, 0, fmt[0], fmt[1], data || null);
    return tex;
  }

  /** Segment i of `model` (decoded) on the GPU. Throws Error when it does not fit this GPU's textures. */
  upload(model, i) {
    const gl = this.gl, s = model.segments[i], d = s.decoded;
    const L = dataLayout(s.positionDegree, s.rotationDegree, s.channels);
    const texels = s.count * L.texels, rows = Math.max(1, Math.ceil(texels / DATA_WIDTH));
    if (rows > this.maxTexture) {
      throw new Error(`segment ${i} has ${s.count} Gaussians, more than this browser's WebGL textures hold `
        + `(${Math.floor((this.maxTexture * DATA_WIDTH) / L.texels)} of this layout)`);
    }
    const data = new Float32Array(rows * DATA_WIDTH * 4), perGaussian = 4 * L.texels;
    const P = 3 * (s.positionDegree + 1), Q = 4 * (s.rotationDegree + 1), C = s.channels;
    for (let g = 0; g < s.count; g++) {
      const o = g * perGaussian;
      data[o] = d.opacity[g]; data[o + 1] = d.t_center[g]; data[o + 2] = d.t_scale[g];
      data[o + 3] = d.scale[3 * g]; data[o + 4] = d.scale[3 * g + 1]; data[o + 5] = d.scale[3 * g + 2];
      data.set(d.position.subarray(P * g, P * g + P), o + L.position);
      data.set(d.rotation.subarray(Q * g, Q * g + Q), o + L.rotation);
      data.set(d.features.subarray(C * g, C * g + C), o + L.features);
    }
    const gpu = { index: i, count: s.count, layout: L, kind: model.kind, instances: 0,
      texture: this.floatTexture(gl.RGBA32F, DATA_WIDTH, rows, data) };
    const key = `${model.kind} ${L.positionDegree} ${L.rotationDegree} ${L.channels}`, sh = splatShaders(model.kind, L);
    gpu.project = this.program(`project ${key}`, { ...sh.project, attributes: ["a_index"] });
    gpu.quad = this.program(`quad ${model.kind}`, sh.quad);
    gpu.points = this.program(`points ${key}`, { ...sh.points, attributes: ["a_index"] });
    gpu.recordTexels = sh.recordTexels;
    if (model.kind === "full") {
      const w = mlpWeights(d.decoder), wrows = Math.ceil(w.length / WEIGHTS_WIDTH);
      const padded = new Float32Array(wrows * WEIGHTS_WIDTH);
      padded.set(w);
      gpu.weights = this.floatTexture(gl.R32F, WEIGHTS_WIDTH, wrows, padded);
      const sources = colourShaders("full", d.decoder, d.activation);  // per decoder: small ones are compiled in
      gpu.colour = this.program(sources.fragment, sources);
    } else {
      gpu.colour = this.program(`colour ${model.kind}`, colourShaders(model.kind, null, null));
    }
    // The projection pass reads the order (one point per Gaussian, nearest first) and writes one record
    // per Gaussian in that order (transform feedback); the quad pass draws one instance per record.
    gpu.order = gl.createBuffer();
    gpu.projectVao = gl.createVertexArray();
    gl.bindVertexArray(gpu.projectVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, gpu.order);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribIPointer(0, 1, gl.UNSIGNED_INT, 0, 0);
    // records: RGBA32F texels, recordTexels per Gaussian; the buffer holds whole rows of the texture
    gpu.recordRows = Math.max(1, Math.ceil((s.count * sh.recordTexels) / RECORD_WIDTH));
    if (gpu.recordRows > this.maxTexture) throw new Error(`segment ${i} has ${s.count} Gaussians, more than this browser's WebGL textures hold`);
    gpu.records = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, gpu.records);
    gl.bufferData(gl.ARRAY_BUFFER, gpu.recordRows * RECORD_WIDTH * 16, gl.DYNAMIC_COPY);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    gl.bindVertexArray(null);
    gpu.recordTexture = this.floatTexture(gl.RGBA32F, RECORD_WIDTH, gpu.recordRows);
    gpu.quadVao = gl.createVertexArray();  // no attributes: the quads read the records texture
    const indices = this.quadIndices(s.count);
    gl.bindVertexArray(gpu.quadVao);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, indices);
    gl.bindVertexArray(null);
    gpu.feedback = gl.createTransformFeedback();
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, gpu.feedback);
    gl.bindBufferBase(gl.TRANSFORM_FEEDBACK_BUFFER, 0, gpu.records);
    gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, null);
    return gpu;
  }

  /** An index buffer of two triangles per quad (corners 4q .. 4q + 3), for at least `count` quads (a
   * smaller earlier one stays with the segments whose vertex arrays hold it). */
  quadIndices(count) {
    const gl = this.gl;
    if (!this.indices || this.indices.count < count) {
      const n = Math.max(count, 1024), data = new Uint32Array(6 * n);
      for (let q = 0; q < n; q++) data.set([4 * q, 4 * q + 1, 4 * q + 2, 4 * q + 1, 4 * q + 2, 4 * q + 3], 6 * q);
      this.indices = { count: n, buffer: gl.createBuffer() };
      gl.bindVertexArray(null);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indices.buffer);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, data, gl.STATIC_DRAW);
    }
    return this.indices.buffer;
  }

  release(gpu) {
    const gl = this.gl;
    gl.deleteTexture(gpu.texture);
    gl.deleteTexture(gpu.recordTexture);
    if (gpu.weights) gl.deleteTexture(gpu.weights);
    gl.deleteBuffer(gpu.order);
    gl.deleteBuffer(gpu.records);
    gl.deleteVertexArray(gpu.projectVao);
    gl.deleteVertexArray(gpu.quadVao);
    gl.deleteTransformFeedback(gpu.feedback);
  }

  setOrder(gpu, order) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, gpu.order);
    gl.bufferData(gl.ARRAY_BUFFER, order, gl.DYNAMIC_DRAW);
    gpu.instances = order.length;
  }

  ensureTargets(width, height) {
    const gl = this.gl;
    if (this.targets && this.targets.width === width && this.targets.height === height) return this.targets;
    if (this.targets) {
      this.targets.features.forEach((t) => gl.deleteTexture(t));
      gl.deleteTexture(this.targets.rgba);
      gl.deleteFramebuffer(this.targets.splatFbo);
      gl.deleteFramebuffer(this.targets.rgbaFbo);
    }
    const features = [0, 1, 2].map(() => this.floatTexture(this.featureFormat, width, height));
    const splatFbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, splatFbo);
    features.forEach((t, k) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + k, gl.TEXTURE_2D, t, 0));
    const rgba = this.floatTexture(gl.RGBA8, width, height);
    const rgbaFbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, rgbaFbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, rgba, 0);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error("WebGL: the colour target is incomplete");
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.targets = { width, height, features, splatFbo, rgba, rgbaFbo };
    return this.targets;
  }

  setCamera(u, uniforms) {
    const gl = this.gl, set = (name, fn, ...v) => { if (uniforms[name]) gl[fn](uniforms[name], ...v); };
    set("u_R0", "uniform3f", u.R[0], u.R[1], u.R[2]);
    set("u_R1", "uniform3f", u.R[3], u.R[4], u.R[5]);
    set("u_R2", "uniform3f", u.R[6], u.R[7], u.R[8]);
    set("u_t", "uniform3f", ...u.t);
    set("u_intr", "uniform4f", ...u.intr);
    set("u_size", "uniform2f", ...u.size);
    set("u_lim", "uniform4f", ...u.lim);
    set("u_fisheye", "uniform1i", u.fisheye);
    set("u_k", "uniform4f", ...u.k);
    set("u_maxAngle", "uniform1f", u.maxAngle);
    set("u_center", "uniform3f", ...u.center);
  }

  /** Render `gpu` (its current order) seen by `camera` at normalised time tau into the canvas, or into
   * pixels (returned: Uint8Array RGBA, top row first). */
  draw(gpu, camera, tau, target = "canvas") {
    const u = cameraUniforms(camera), t = this.ensureTargets(camera.width, camera.height);
    this.splat(gpu, camera, u, tau, t);
    this.colour(gpu, camera, u, t, target === "canvas" ? null : t.rgbaFbo, target === "canvas");
    return this.finish(camera, target, t);
  }

  /** Inside a crossfade: parts [{gpu, tau, weight}, {gpu, tau, weight}] (stg-format.js segmentsAt, the
   * earlier segment first; weights add up to 1), each rendered to its rgb in a float texture, then
   * shown as (1 - w) A + w B, w the later segment's weight. Returns as draw. */
  drawCrossfade(parts, camera, target = "canvas") {
    const gl = this.gl, u = cameraUniforms(camera), t = this.ensureTargets(camera.width, camera.height);
    const fade = this.ensureFadeTargets(camera.width, camera.height);
    parts.forEach((part, k) => {
      this.splat(part.gpu, camera, u, part.tau, t);
      this.colour(part.gpu, camera, u, t, fade.fbos[k], false);
    });
    const mix = this.program("crossfade", crossfadeShaders());
    this.bindTarget(camera, target === "canvas" ? null : t.rgbaFbo);
    gl.useProgram(mix.program);
    gl.uniform1i(mix.uniforms.u_flip, target === "canvas" ? 1 : 0);
    gl.uniform1f(mix.uniforms.u_height, camera.height);
    gl.uniform1f(mix.uniforms.u_w, parts[1].weight);
    fade.textures.forEach((tex, k) => {
      gl.activeTexture(gl.TEXTURE0 + k);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.uniform1i(mix.uniforms[k ? "u_b" : "u_a"], k);
    });
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    return this.finish(camera, target, t);
  }

  /** Two RGBA32F targets of the camera's size for the two segments' rgb of a crossfade (made on the
   * first crossfade, kept while the size stays). */
  ensureFadeTargets(width, height) {
    const gl = this.gl;
    if (this.fade && this.fade.width === width && this.fade.height === height) return this.fade;
    if (this.fade) {
      this.fade.textures.forEach((tex) => gl.deleteTexture(tex));
      this.fade.fbos.forEach((fbo) => gl.deleteFramebuffer(fbo));
    }
    const textures = [0, 1].map(() => this.floatTexture(gl.RGBA32F, width, height));
    const fbos = textures.map((tex) => {
      const fbo = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error("WebGL: the crossfade target is incomplete");
      return fbo;
    });
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.fade = { width, height, textures, fbos };
    return this.fade;
  }

  /** Bind the canvas (fbo null; sized to the camera) or `fbo` as the render target, viewport the camera's. */
  bindTarget(camera, fbo) {
    const gl = this.gl, W = camera.width, H = camera.height;
    if (fbo === null && (this.canvas.width !== W || this.canvas.height !== H)) { this.canvas.width = W; this.canvas.height = H; }
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.viewport(0, 0, W, H);
  }

  /** After the last pass: null for the canvas, else the pixels of t.rgbaFbo (RGBA, top row first). */
  finish(camera, target, t) {
    const gl = this.gl;
    if (target === "canvas") return null;
    const pixels = new Uint8Array(camera.width * camera.height * 4);
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.rgbaFbo);
    gl.readPixels(0, 0, camera.width, camera.height, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return pixels;
  }

  /** Passes 1 and 2: `gpu` (its current order) at tau, its features splatted into the targets t. */
  splat(gpu, camera, u, tau, t) {
    const gl = this.gl, W = camera.width, H = camera.height, n = gpu.instances;
    if (this.pointsFit(W, H)) {  // one pass: a point sprite per Gaussian, projected by its vertex shader
      this.bindSplatTargets(gpu, W, H, t);
      if (n) {
        gl.enable(gl.BLEND);
        gl.blendFunc(gl.ONE_MINUS_DST_ALPHA, gl.ONE);  // front to back: dst += T src, T = 1 - dst alpha
        this.useGaussianProgram(gpu.points, gpu, u, tau);
        gl.bindVertexArray(gpu.projectVao);
        gl.drawArrays(gl.POINTS, 0, n);
        gl.bindVertexArray(null);
        gl.disable(gl.BLEND);
      }
      return;
    }
    // 1. time evaluation and footprints, one record per Gaussian in depth order
    this.useGaussianProgram(gpu.project, gpu, u, tau);
    if (n) {
      gl.enable(gl.RASTERIZER_DISCARD);
      gl.bindVertexArray(gpu.projectVao);
      gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, gpu.feedback);
      gl.beginTransformFeedback(gl.POINTS);
      gl.drawArrays(gl.POINTS, 0, n);
      gl.endTransformFeedback();
      gl.bindTransformFeedback(gl.TRANSFORM_FEEDBACK, null);
      gl.disable(gl.RASTERIZER_DISCARD);
      gl.bindBuffer(gl.PIXEL_UNPACK_BUFFER, gpu.records);  // records -> texture, on the GPU
      gl.bindTexture(gl.TEXTURE_2D, gpu.recordTexture);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, RECORD_WIDTH, Math.ceil((n * gpu.recordTexels) / RECORD_WIDTH), gl.RGBA, gl.FLOAT, 0);
      gl.bindBuffer(gl.PIXEL_UNPACK_BUFFER, null);
    }
    // 2. the features, splatted front to back
    this.bindSplatTargets(gpu, W, H, t);
    if (n) {
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE_MINUS_DST_ALPHA, gl.ONE);  // front to back: dst += T src, T = 1 - dst alpha
      gl.useProgram(gpu.quad.program);
      gl.uniform2f(gpu.quad.uniforms.u_size, W, H);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, gpu.recordTexture);
      gl.uniform1i(gpu.quad.uniforms.u_records, 0);
      gl.bindVertexArray(gpu.quadVao);
      gl.drawElements(gl.TRIANGLES, 6 * n, gl.UNSIGNED_INT, 0);
      gl.bindVertexArray(null);
      gl.disable(gl.BLEND);
    }
  }

  /** `program` (one that reads the Gaussians: the projection or the point sprites) in use, with the
   * camera uniforms u, the time tau and `gpu`'s Gaussian texture on unit 0. */
  useGaussianProgram(program, gpu, u, tau) {
    const gl = this.gl;
    gl.useProgram(program.program);
    this.setCamera(u, program.uniforms);
    gl.uniform1f(program.uniforms.u_tau, tau);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, gpu.texture);
    gl.uniform1i(program.uniforms.u_data, 0);
  }

  /** The feature targets t bound (the ones `gpu`'s kind writes) and cleared. */
  bindSplatTargets(gpu, W, H, t) {
    const gl = this.gl, outputs = gpu.kind === "full" ? 3 : 1;
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.splatFbo);
    gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1, gl.COLOR_ATTACHMENT2].map((b, k) => (k < outputs ? b : gl.NONE)));
    gl.viewport(0, 0, W, H);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
  }

  /** Pass 3, colour: the features in the targets t -> rgb into `fbo` (null: the canvas), rows flipped
   * when `flip` (the canvas shows the top row first). */
  colour(gpu, camera, u, t, fbo, flip) {
    const gl = this.gl, outputs = gpu.kind === "full" ? 3 : 1;
    const colour = gpu.colour;
    this.bindTarget(camera, fbo);
    gl.useProgram(colour.program);
    this.setCamera(u, colour.uniforms);
    gl.uniform1i(colour.uniforms.u_flip, flip ? 1 : 0);
    const textures = [...t.features.slice(0, outputs), ...(gpu.weights ? [gpu.weights] : [])];
    ["u_f0", "u_f1", "u_f2"].slice(0, outputs).concat(gpu.weights ? ["u_weights"] : []).forEach((name, k) => {
      gl.activeTexture(gl.TEXTURE0 + k);
      gl.bindTexture(gl.TEXTURE_2D, textures[k]);
      gl.uniform1i(colour.uniforms[name], k);
    });
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }
}
