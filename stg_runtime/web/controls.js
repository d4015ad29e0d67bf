// Camera controls of the page: orbit, pan and dolly by mouse and touch, fly and look by keys. They move
// the pose of the player's camera (world_to_camera, OpenCV axes: x right, y down, z forward) and keep
// its intrinsics and size.

function rotation(axis, angle) {  // Rodrigues: the 3x3 rotation (row-major) by `angle` about unit `axis`
  const [x, y, z] = axis, c = Math.cos(angle), s = Math.sin(angle), k = 1 - c;
  return [c + x * x * k, x * y * k - z * s, x * z * k + y * s, y * x * k + z * s, c + y * y * k, y * z * k - x * s,
    z * x * k - y * s, z * y * k + x * s, c + z * z * k];
}
const apply = (M, v) => [0, 1, 2].map((i) => M[3 * i] * v[0] + M[3 * i + 1] * v[1] + M[3 * i + 2] * v[2]);
const row = (R, i) => R.slice(3 * i, 3 * i + 3);

/** A pose: R (rows = the camera's x, y, z axes in world coordinates) and centre C. */
export function poseOf(w2c) {
  const R = [w2c[0], w2c[1], w2c[2], w2c[4], w2c[5], w2c[6], w2c[8], w2c[9], w2c[10]], t = [w2c[3], w2c[7], w2c[11]];
  const C = [0, 1, 2].map((j) => -(R[j] * t[0] + R[3 + j] * t[1] + R[6 + j] * t[2]));
  return { R, C };
}

export function worldToCamera({ R, C }) {
  const t = [0, 1, 2].map((i) => -(R[3 * i] * C[0] + R[3 * i + 1] * C[1] + R[3 * i + 2] * C[2]));
  return [R[0], R[1], R[2], t[0], R[3], R[4], R[5], t[1], R[6], R[7], R[8], t[2], 0, 0, 0, 1];
}

function rotatePose(pose, M, about) {  // rotate the camera by world rotation M about point `about`
  const R = [...apply(M, row(pose.R, 0)), ...apply(M, row(pose.R, 1)), ...apply(M, row(pose.R, 2))];
  const d = apply(M, [0, 1, 2].map((k) => pose.C[k] - about[k]));
  return { R, C: [0, 1, 2].map((k) => about[k] + d[k]) };
}

export class Controls {
  /** player: StgPlayer; element: the canvas; distance: initial orbit distance (world units). */
  constructor(player, element, distance = 2) {
    this.player = player;
    this.element = element;
    this.distance = distance;
    this.keys = new Set();
    this.pointers = new Map();
    this.up = null;
    element.addEventListener("contextmenu", (e) => e.preventDefault());
    element.addEventListener("pointerdown", (e) => this.down(e));
    element.addEventListener("pointermove", (e) => this.move(e));
    for (const type of ["pointerup", "pointercancel", "pointerleave"]) element.addEventListener(type, (e) => this.pointers.delete(e.pointerId));
    element.addEventListener("wheel", (e) => { e.preventDefault(); this.dolly(Math.exp(e.deltaY * 0.001)); }, { passive: false });
    element.tabIndex = 0;
    element.addEventListener("keydown", (e) => { if (this.handles(e.key)) { this.keys.add(e.key.toLowerCase()); e.preventDefault(); } });
    element.addEventListener("keyup", (e) => this.keys.delete(e.key.toLowerCase()));
    element.addEventListener("blur", () => this.keys.clear());
    this.last = performance.now();
    requestAnimationFrame((t) => this.fly(t));
  }

  /** Call when the camera was set from outside (a preset): the world's up becomes this camera's -y. */
  reset(distance) {
    if (distance) this.distance = distance;
    this.up = null;
  }

  handles(key) { return ["w", "a", "s", "d", "q", "e", "arrowup", "arrowdown", "arrowleft", "arrowright"].includes(key.toLowerCase()); }

  pose() {
    const pose = poseOf(this.player.cam.worldToCamera);
    if (!this.up) this.up = row(pose.R, 1).map((v) => -v);
    return pose;
  }

  target(pose) { const z = row(pose.R, 2); return [0, 1, 2].map((k) => pose.C[k] + this.distance * z[k]); }
  set(pose) { this.player.setPose(worldToCamera(pose)); }

  orbit(dx, dy) {  // pixels of drag
    let pose = this.pose();
    const target = this.target(pose);
    pose = rotatePose(pose, rotation(this.up, -dx * 0.005), target);
    pose = rotatePose(pose, rotation(row(pose.R, 0), dy * 0.005), target);
    this.set(pose);
  }

  pan(dx, dy) {
    const pose = this.pose(), step = (this.distance * 0.5) / this.element.clientHeight;
    const x = row(pose.R, 0), y = row(pose.R, 1);
    this.set({ R: pose.R, C: [0, 1, 2].map((k) => pose.C[k] - step * (dx * x[k] + dy * y[k]) * 2) });
  }

  dolly(factor) {
    const pose = this.pose(), target = this.target(pose), z = row(pose.R, 2);
    this.distance = Math.max(1e-3, this.distance * factor);
    this.set({ R: pose.R, C: [0, 1, 2].map((k) => target[k] - this.distance * z[k]) });
  }

  down(e) {
    this.element.focus();
    this.element.setPointerCapture(e.pointerId);
    this.pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey });
  }

  move(e) {
    const p = this.pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x, dy = e.clientY - p.y;
    if (this.pointers.size === 2) {  // pinch: dolly by the change of the fingers' distance, pan by their motion
      const [a, b] = [...this.pointers.values()];
      const before = Math.hypot(a.x - b.x, a.y - b.y);
      p.x = e.clientX; p.y = e.clientY;
      const after = Math.hypot(a.x - b.x, a.y - b.y);
      if (before > 0 && after > 0) this.dolly(before / after);
      this.pan(dx / 2, dy / 2);
      return;
    }
    p.x = e.clientX; p.y = e.clientY;
    if (p.button === 2 || p.button === 1 || p.shift) this.pan(dx, dy);
    else this.orbit(dx, dy);
  }

  fly(now) {
    const dt = Math.min(0.1, (now - this.last) / 1000);
    this.last = now;
    requestAnimationFrame((t) => this.fly(t));
    if (!this.keys.size || !this.player.cam) return;
    let pose = this.pose();
    const speed = this.distance * dt, turn = 1.2 * dt, k = this.keys;
    const move = [(k.has("d") ? 1 : 0) - (k.has("a") ? 1 : 0), (k.has("q") ? 1 : 0) - (k.has("e") ? 1 : 0),
      (k.has("w") ? 1 : 0) - (k.has("s") ? 1 : 0)];
    const world = [0, 1, 2].map((j) => speed * (pose.R[j] * move[0] + pose.R[3 + j] * move[1] + pose.R[6 + j] * move[2]));
    pose = { R: pose.R, C: pose.C.map((c, j) => c + world[j]) };
    const yaw = (k.has("arrowleft") ? 1 : 0) - (k.has("arrowright") ? 1 : 0);
    const pitch = (k.has("arrowup") ? 1 : 0) - (k.has("arrowdown") ? 1 : 0);
    if (yaw) pose = rotatePose(pose, rotation(this.up, -yaw * turn), pose.C);
    if (pitch) pose = rotatePose(pose, rotation(row(pose.R, 0), pitch * turn), pose.C);
    this.set(pose);
  }
}
