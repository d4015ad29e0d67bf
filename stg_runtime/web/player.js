// StgPlayer: a .stg model played in a <canvas> with WebGL2; the API the page, embedders and the tests use.
//
//   const player = new StgPlayer(canvas, {onStatus, onError});
//   await player.load(url | ArrayBuffer | Uint8Array | Blob, name?)   reads the file (stg-format.js)
//   player.setCamera(cam)      cam: one entry of a camera-path JSON file (stg_runtime.camera.save_camera_path),
//                              i.e. a camera object of formats/stg-v1.md; the canvas takes its width x height
//   player.setTime(seconds)    clamped to the model's span
//   await player.snapshot()    ImageData (RGBA, top row first) of a complete frame at the camera's own
//                              size, rendered once the depth order for that camera and time is sorted
//   player.play(), pause(), speed, loop, time, camera (JSON), cameras (the file's, JSON), fps (measured)
//
// Each displayed frame uses the latest depth order the sort worker returned: it may be a few frames old
// while the view or the time changes (docs/web.md, "Sorting"); snapshot() always waits for its own.
// Inside a crossfade (format 1.3, stg-format.js segmentsAt) both segments are sorted and drawn, and the
// frame is (1 - w) A + w B (renderer.js drawCrossfade).

import { DEFAULT_LIMITS, FormatError, parseCamera, readStg, segmentAt, segmentsAt } from "./stg-format.js";
import { openRanged } from "./stream.js";
import { Renderer } from "./renderer.js";

function cameraJson(c) {
  const intr = { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy };
  const base = { name: c.name, width: c.width, height: c.height };
  if (c.model === "fisheye") {
    return { ...base, model: "fisheye", intrinsics: { ...intr, k1: c.k[0], k2: c.k[1], k3: c.k[2], k4: c.k[3] },
      world_to_camera: c.worldToCamera.slice() };
  }
  return { ...base, ...intr, world_to_camera: c.worldToCamera.slice() };
}

export class StgPlayer {
  constructor(canvas, { onStatus = () => {}, onError = () => {}, onFrame = () => {}, limits = DEFAULT_LIMITS } = {}) {
    this.canvas = canvas;
    this.onStatus = onStatus;
    this.onError = onError;
    this.onFrame = onFrame;
    this.limits = limits;
    this.renderer = new Renderer(canvas);
    this.worker = new Worker(new URL("./sort-worker.js", import.meta.url), { type: "module" });
    this.worker.onmessage = (e) => this.sorted(e.data);
    this.worker.onerror = (e) => this.fail(new Error(`the sort worker failed: ${e.message}`));
    this.model = null;
    this.gpu = new Map();           // segment index -> uploaded segment
    this.loading = new Map();
    this.file = null;               // a RangedFile (stream.js) when segments arrive by range requests
    this.pending = new Map();       // sort id -> resolve
    this.nextId = 1;
    this.inFlight = 0;              // display sorts requested and not yet answered
    this.sortedFor = null;          // the key of the last sort requested for display
    this.cam = null;
    this.t = 0;
    this.playing = false;
    this.speed = 1;
    this.loop = true;
    this.fps = 0;
    this.sortMs = 0;
    this.frames = 0;
    this.fpsStart = performance.now();
    this.lastTick = null;
    this.error = null;
    this.stats = { firstFrameMs: null };  // ms from the page's start to the first frame on the canvas
    this.framesTotal = 0;
    this.drawn = null;          // what the canvas shows: view, time and order
    this.continuous = false;    // draw every animation frame even when nothing changed (benchmarks)
    this.raf = requestAnimationFrame((now) => this.tick(now));
  }

  fail(error) {
    this.error = error.message;
    this.playing = false;
    this.onError(error.message);
    return error;
  }

  /** Read a model: a URL (fetched), or the file's bytes. Rejects (and calls onError) with a readable message. */
  async load(source, name) {
    const started = performance.now();
    try {
      this.reset();
      let model;
      if (typeof source === "string") {
        name = name || decodeURIComponent(new URL(source, location.href).pathname.split("/").pop() || source);
        this.onStatus(`fetching ${name}`);
        const opened = await openRanged(source, name, this.limits);  // segments by range requests where served
        model = opened.model;
        this.file = opened.file || null;
        this.stats.bytes = opened.file ? opened.file.sentBytes : opened.whole.length;
      } else {
        let bytes;
        if (source instanceof Blob) {
          name = name || source.name || "<file>";
          bytes = new Uint8Array(await source.arrayBuffer());
        } else {
          bytes = source instanceof Uint8Array ? source : new Uint8Array(source);
          name = name || "<bytes>";
        }
        this.onStatus(`reading ${name}`);
        model = await readStg(bytes, name, this.limits);
        this.stats.bytes = bytes.length;
      }
      this.model = model;
      this.stats.loadMs = performance.now() - started;
      this.t = model.startTime;
      if (model.cameras.length) this.cam = model.cameras[0];
      else this.cam = this.defaultCamera(model);
      this.onStatus(`${name}: ${model.kind}, ${model.segments.length} segment(s), ${model.segments.reduce((n, s) => n + s.count, 0)} Gaussians`);
      return this.info();
    } catch (e) {
      throw this.fail(e);
    }
  }

  reset() {
    for (const gpu of this.gpu.values()) this.renderer.release(gpu);
    this.gpu.clear();
    this.loading = new Map();       // segment index -> Promise of its upload
    this.shownSegment = -1;
    this.file = null;
    this.model = null;
    this.error = null;
    this.sortedFor = null;
    this.worker.postMessage({ type: "forget-all" });
  }

  defaultCamera(model) {
    const b = model.bounds || { min: [-1, -1, -1], max: [1, 1, 1] };
    const c = [0, 1, 2].map((k) => 0.5 * (b.min[k] + b.max[k]));
    const r = Math.max(...[0, 1, 2].map((k) => b.max[k] - b.min[k]), 1e-3);
    return { name: "default", width: 640, height: 360, fx: 500, fy: 500, cx: 320, cy: 180, model: "pinhole", k: [0, 0, 0, 0],
      worldToCamera: [1, 0, 0, -c[0], 0, 1, 0, -c[1], 0, 0, 1, -c[2] + 1.5 * r, 0, 0, 0, 1] };
  }

  info() {
    const m = this.model;
    return { name: m.name, kind: m.kind, fps: m.fps, numFrames: m.numFrames, startTime: m.startTime, duration: m.duration,
      segments: m.segments.length, gaussians: m.segments.map((s) => s.count), cameras: this.cameras };
  }

  get cameras() { return this.model ? this.model.cameras.map(cameraJson) : []; }
  get camera() { return this.cam ? cameraJson(this.cam) : null; }
  get time() { return this.t; }
  get endTime() { return this.model ? this.model.startTime + this.model.duration : 0; }

  /** cam: a camera object of formats/stg-v1.md (one entry of a camera-path JSON file). */
  setCamera(cam) {
    this.cam = parseCamera(cam, this.limits);
  }

  /** The pose part of the camera only (the controls): worldToCamera, 16 numbers row-major. */
  setPose(worldToCamera) {
    this.cam = { ...this.cam, worldToCamera: worldToCamera.slice() };
  }

  setTime(seconds) {
    if (!this.model) return;
    this.t = Math.min(Math.max(Number(seconds), this.model.startTime), this.endTime);
  }

  play() { this.playing = true; }
  pause() { this.playing = false; }

  /** Segment i decoded (fetched first when the file arrives by ranges) and uploaded; a Promise. */
  ensureSegment(i) {
    if (this.gpu.has(i)) return Promise.resolve(this.gpu.get(i));
    if (!this.loading.has(i)) {
      const model = this.model;
      const ready = (this.file ? this.file.segment(i) : Promise.resolve(model.segments[i].decoded)).then(() => {
        if (model !== this.model) return null;  // another model was loaded meanwhile
        const s = model.segments[i];
        const gpu = this.renderer.upload(model, i);
        gpu.firstSortId = this.nextId;  // orders sorted before this upload are not its own
        this.gpu.set(i, gpu);
        this.worker.postMessage({ type: "segment", key: i, count: s.count, positionDegree: s.positionDegree,
          opacity: s.decoded.opacity, t_center: s.decoded.t_center, t_scale: s.decoded.t_scale, position: s.decoded.position });
        this.loading.delete(i);
        return gpu;
      });
      ready.catch((e) => { this.loading.delete(i); this.fail(e); });
      this.loading.set(i, ready);
    }
    return this.loading.get(i);
  }

  /** Keep segments i - 1 .. i + 1 on the GPU (and decoded, for ranged files); fetch i + 1 ahead. */
  keepAround(i) {
    for (const [k, gpu] of this.gpu) {
      if (Math.abs(k - i) <= 1) continue;
      this.renderer.release(gpu);
      this.gpu.delete(k);
      this.worker.postMessage({ type: "forget", key: k });
      if (this.file) this.file.release(k);
    }
    if (i + 1 < this.model.segments.length) this.ensureSegment(i + 1).catch(() => {});
  }

  /** The uploaded segment holding the current time, {gpu, index, tau, parts}, with parts what the time
   * shows: [{gpu, index, tau, weight}], that segment, or two inside a crossfade (segmentsAt); null while
   * one of them is being fetched. */
  current() {
    const parts = segmentsAt(this.model, this.t);
    const missing = parts.filter((p) => !this.gpu.has(p.index));
    if (missing.length) {
      for (const p of missing) this.ensureSegment(p.index).catch(() => {});
      this.onStatus(`loading segment ${missing[0].index + 1} of ${this.model.segments.length}`);
      this.waiting = true;
      return null;
    }
    const { index, tau } = segmentAt(this.model, this.t);  // (a crossfade's other segment is its neighbour)
    if (index !== this.shownSegment) {
      this.shownSegment = index;
      this.keepAround(index);
    }
    if (this.waiting) { this.waiting = false; this.onStatus(""); }
    return { gpu: this.gpu.get(index), index, tau, parts: parts.map((p) => ({ ...p, gpu: this.gpu.get(p.index) })) };
  }

  requestSort(index, tau) {
    const id = this.nextId++;
    const m = this.cam.worldToCamera;
    this.worker.postMessage({ type: "sort", id, key: index, tau, R: [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]],
      t: [m[3], m[7], m[11]] });
    return id;
  }

  sorted(result) {
    this.sortMs = result.sortMs;
    const gpu = this.gpu.get(result.key);
    if (gpu && result.id >= gpu.firstSortId && (!gpu.orderId || result.id > gpu.orderId)) {
      this.renderer.setOrder(gpu, result.order);
      gpu.orderId = result.id;
    }
    const resolve = this.pending.get(result.id);
    if (resolve) { this.pending.delete(result.id); resolve(result); } else this.inFlight = Math.max(0, this.inFlight - 1);
  }

  /** ImageData of a complete frame at the camera's own size, sorted for exactly this camera and time. */
  async snapshot() {
    if (!this.model) throw new Error("no model loaded");
    const parts = segmentsAt(this.model, this.t);
    const gpus = await Promise.all(parts.map((p) => this.ensureSegment(p.index)));
    if (this.error) throw new Error(this.error);
    const cam = this.cam;
    const ids = parts.map((p) => this.requestSort(p.index, p.tau));
    const results = await Promise.all(ids.map((id) => new Promise((resolve) => this.pending.set(id, resolve))));
    results.forEach((result, k) => {
      this.renderer.setOrder(gpus[k], result.order);
      gpus[k].orderId = Math.max(gpus[k].orderId || 0, ids[k]);
    });
    const pixels = parts.length === 1 ? this.renderer.draw(gpus[0], cam, parts[0].tau, "pixels")
      : this.renderer.drawCrossfade(parts.map((p, k) => ({ ...p, gpu: gpus[k] })), cam, "pixels");
    return new ImageData(new Uint8ClampedArray(pixels.buffer), cam.width, cam.height);
  }

  tick(now) {
    this.raf = requestAnimationFrame((n) => this.tick(n));
    if (!this.model || this.error || !this.cam) { this.lastTick = now; return; }
    try {
      if (this.playing && this.lastTick !== null) {
        let t = this.t + ((now - this.lastTick) / 1000) * this.speed;
        if (t > this.endTime) {
          if (this.loop) t = this.model.startTime + ((t - this.model.startTime) % this.model.duration);
          else { t = this.endTime; this.playing = false; }
        }
        this.t = t;
      }
      this.lastTick = now;
      if (now - this.fpsStart >= 1000) {  // frames drawn per second (0 while nothing changes)
        this.fps = (1000 * this.frames) / (now - this.fpsStart);
        this.frames = 0;
        this.fpsStart = now;
        this.onFrame(this);
      }
      const shown = this.current();
      if (!shown) return;
      const { parts } = shown;
      const key = `${parts.map((p) => `${p.index} ${p.tau}`).join(" ")} ${this.cam.worldToCamera.join(",")}`;
      if (key !== this.sortedFor && !this.inFlight) {
        this.sortedFor = key;
        this.inFlight = parts.length;
        for (const p of parts) this.requestSort(p.index, p.tau);
      }
      if (!parts.every((p) => p.gpu.orderId)) return;
      const drawn = `${key} ${parts.map((p) => p.gpu.orderId).join(" ")}`;
      if (drawn === this.drawn && !this.continuous) return;  // nothing changed since the last frame
      this.drawn = drawn;
      if (parts.length === 1) this.renderer.draw(parts[0].gpu, this.cam, parts[0].tau, "canvas");
      else this.renderer.drawCrossfade(parts, this.cam, "canvas");
      if (this.stats.firstFrameMs === null) {  // ms since the page's navigation began, the frame finished
        this.renderer.gl.readPixels(0, 0, 1, 1, this.renderer.gl.RGBA, this.renderer.gl.UNSIGNED_BYTE, new Uint8Array(4));  // waits for it
        this.stats.firstFrameMs = performance.now();
      }
      this.frames++;
      this.framesTotal++;
      this.onFrame(this);
    } catch (e) {
      this.fail(e);
    }
  }
}
