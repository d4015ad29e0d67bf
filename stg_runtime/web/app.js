// The page (index.html): the player, its controls, and window.stg, the API for embedding and tests.
//
// The model comes from ?model=URL, else from <meta name="stg-model" content="...">, else model.stg;
// ?camera=K starts at training camera K, ?t=SECONDS at that time, ?play=1 plays.
// window.stg: {player, ready (a Promise, settled once the first load ends), load(url), setCamera(cam),
// setTime(s), snapshot() -> Promise<{width, height, data: Uint8ClampedArray RGBA top row first}>,
// snapshotBase64() (the same pixels as base64, for drivers such as selenium), message (the text shown)}.

import { StgPlayer } from "./player.js";
import { Controls } from "./controls.js";

const $ = (id) => document.getElementById(id);
const canvas = $("view"), message = $("message");

function show(text, isError = false) {
  message.textContent = text;
  message.className = isError ? "error" : text ? "status" : "";
  window.stg.message = text;
  window.stg.error = isError ? text : null;
}

window.stg = { message: "", error: null };
let player, controls;
try {
  player = new StgPlayer(canvas, {
    onStatus: (text) => show(text),
    onError: (text) => show(text, true),
    onFrame: () => frame(),
  });
} catch (e) {
  show(e.message, true);
}

const params = new URLSearchParams(location.search);
const modelUrl = params.get("model") || document.querySelector('meta[name="stg-model"]')?.content || "model.stg";

function fmt(t) { return t.toFixed(2); }

let lastUi = 0;
function frame() {
  const now = performance.now();
  if (now - lastUi < 100) return;
  lastUi = now;
  $("fps").textContent = `${player.fps.toFixed(1)} fps`;
  const slider = $("time");
  if (document.activeElement !== slider) slider.value = player.time;
  $("clock").textContent = `${fmt(player.time)} / ${fmt(player.endTime)} s`;
  $("play").textContent = player.playing ? "pause" : "play";
}

function orbitDistance(info) {
  const b = player.model.bounds, cam = player.cam;
  if (!b || !cam) return 2;
  const m = cam.worldToCamera, centre = [0, 1, 2].map((k) => 0.5 * (b.min[k] + b.max[k]));
  const z = m[8] * centre[0] + m[9] * centre[1] + m[10] * centre[2] + m[11];  // depth of the bounds' centre
  return z > 1e-3 ? z : 2;
}

async function load(url) {
  const info = await player.load(url);
  const presets = $("presets");
  presets.innerHTML = "";
  info.cameras.forEach((c, k) => presets.add(new Option(c.name || `camera ${k}`, String(k))));
  presets.disabled = !info.cameras.length;
  const slider = $("time");
  slider.min = info.startTime;
  slider.max = info.startTime + info.duration;
  slider.step = 1 / info.fps / 4;
  const k = Number(params.get("camera") || 0);
  if (info.cameras[k]) { player.setCamera(info.cameras[k]); presets.value = String(k); }
  if (params.has("t")) player.setTime(Number(params.get("t")));
  if (params.get("play") === "1") player.play();
  if (!controls) controls = new Controls(player, canvas, orbitDistance(info));
  else controls.reset(orbitDistance(info));
  show("");
  return info;
}

if (player) {
  Object.assign(window.stg, {
    player,
    load,
    setCamera: (cam) => { player.setCamera(cam); controls?.reset(); },
    setTime: (s) => player.setTime(s),
    snapshot: async () => {
      const image = await player.snapshot();
      return { width: image.width, height: image.height, data: image.data };
    },
    snapshotBase64: async () => {
      const { width, height, data } = await window.stg.snapshot();
      let text = "";
      for (let i = 0; i < data.length; i += 0x8000) text += String.fromCharCode(...data.subarray(i, i + 0x8000));
      return { width, height, data: btoa(text) };
    },
  });
  $("play").onclick = () => (player.playing ? player.pause() : player.play());
  $("time").oninput = (e) => player.setTime(Number(e.target.value));
  $("speed").onchange = (e) => { player.speed = Number(e.target.value); };
  $("loop").onchange = (e) => { player.loop = e.target.checked; };
  const preset = () => {
    const cam = player.cameras[Number($("presets").value)];
    if (cam) { player.setCamera(cam); controls?.reset(orbitDistance()); }
  };
  $("presets").onchange = preset;
  $("reset").onclick = preset;
  $("open").onchange = (e) => e.target.files[0] && load(e.target.files[0]).catch(() => {});
  document.addEventListener("keydown", (e) => {
    if (e.key === " " && e.target.tagName !== "INPUT") { e.preventDefault(); $("play").click(); }
  });
  canvas.addEventListener("dragover", (e) => e.preventDefault());
  canvas.addEventListener("drop", (e) => { e.preventDefault(); if (e.dataTransfer.files[0]) load(e.dataTransfer.files[0]).catch(() => {}); });
  window.stg.ready = load(modelUrl).catch((e) => e);
} else {
  window.stg.ready = Promise.resolve(new Error(window.stg.error));
}
