// Feasibility probe (docs/web.md, "What remains"): a tile compositor in WebAssembly SIMD (f32x4, 4
// pixels per op), timed on the benchmark frame that bench/web_wasm_probe.py dumps from the CPU
// Player's own steps, and a plain-JS front end (time evaluation, projection, sort, binning) for the
// rest of a page frame. Not part of the web player; node 20, no browser. Needs the npm package wabt
// (not a project dependency) to assemble the WAT that it generates:
//
//   npm install --prefix /tmp/wabt wabt
//   WABT=/tmp/wabt/node_modules/wabt python bench/web_wasm_probe.py   # dumps the frame, drives this file
//   WABT=/tmp/wabt/node_modules/wabt node --no-liftoff --experimental-wasm-relaxed-simd \
//       bench/web_wasm_probe.mjs /tmp/stg-wasm-probe                  # alone, after a dump
//
// The kernel follows stg_runtime/splat_cpu.py's _composite for lite (3 channels): 16x16 tiles taken
// from an atomic counter in the order given (longest list first); a tile's state (T, negated once the
// pixel stopped; sum w z; sum w f x 3) in row-major planes, 4 groups of 4 pixels per row; per Gaussian
// of the tile's depth-ordered list, its pixel rectangle clipped to the tile, two rows at a time (dx
// and A/2 dx shared), the groups from its first to its last column, pixels outside the rectangle
// masked; the spec's rules branch-free (alpha = min(0.99, o exp(-power)), skip alpha < 1/255 and
// power < 0, stop when T (1 - alpha) < 1e-4 without adding); exp(-p) as splat_cpu.exp_neg (Cody-Waite,
// degree-6 polynomial, exponent bits); a tile ends once all its pixels have stopped. Records are
// splat_cpu's 64-byte ones (mean, conic A/2, B, C/2, opacity, z, thr, rectangle, rgb), read by id.
// Two builds: "simd" (standard SIMD) and "fma" (relaxed SIMD's relaxed_madd for the polynomial, the
// power and the sums; Chromium 114+ ships it, node 20 needs --experimental-wasm-relaxed-simd).
// Tried and left out (slower on this frame): one row at a time (about 10%); visiting only each
// row's chord of the ellipse (22% fewer groups, but the chord's float64 sqrt per row cost more);
// skipping rows whose pixels have all stopped (the stop skips 0.02-0.11% of this scene's work).
//
// "--serve DIR" (as the .py drives it): commands on stdin, one line each, answered by one line on
// stdout: "kinds" (the builds here), "check" (each build's image against the dump: max abs
// differences and PSNR; 1 and 2 threads the same bits; the front end's tile-list entries against
// numba's), "c1 KIND" (ms of one frame's compositing on this thread), "c2 KIND" (the same on 2 worker
// threads sharing the memory), "copy" (ms to post the records and tile lists to a worker, copied as
// postMessage does, and an RGBA image back), "front" (ms of the JS front end, one thread).
import { createRequire } from 'node:module';
import { readFileSync } from 'node:fs';
import { Worker, isMainThread, parentPort, workerData } from 'node:worker_threads';
import { performance } from 'node:perf_hooks';

// f32x4 constants: each is a local, set once on entry (measured no faster or slower than v128.const
// in the loop, which V8 builds with several instructions at each use).
const CONSTS = new Map();
const vconst = (v) => {
  if (!CONSTS.has(String(v))) CONSTS.set(String(v), `$k${CONSTS.size}`);
  return `(local.get ${CONSTS.get(String(v))})`;
};
const constLocals = () => [...CONSTS.entries()].map(([, name]) => `(local ${name} v128)`).join(' ');
const constInits = () => [...CONSTS.entries()].map(([v, name]) => `(local.set ${name} (v128.const f32x4 ${v} ${v} ${v} ${v}))`).join('\n   ');

// exp(-p) for p <= 87 (larger p clamped), as splat_cpu.exp_neg, on the v128 in local $p -> $e: the
// same operations in float32 (the sign folded into the constants: x = -p is never formed, which
// rounds the same); 2^n from the low bits of n + 1.5 * 2^23 + 127 shifted into the exponent.
let FMA = false;
const madd = (a, b, c) => FMA ? `(f32x4.relaxed_madd ${a} ${b} ${c})` : `(f32x4.add (f32x4.mul ${a} ${b}) ${c})`;
const expNeg = () => `
  (local.set $x (f32x4.pmin (local.get $p) ${vconst(87)}))
  (local.set $n (f32x4.floor (f32x4.add (f32x4.mul (local.get $x) ${vconst(-1.4426950408889634)}) ${vconst(0.5)})))
  (local.set $x (f32x4.sub (f32x4.sub (f32x4.mul (local.get $n) ${vconst(-0.693359375)}) (local.get $x))
                           (f32x4.mul (local.get $n) ${vconst(-2.1219444005469057e-4)})))
  (local.set $e ${vconst(0.0013941213136701553)})
  ${[0.008375210201056223, 0.0416663516378278, 0.16666414507167096, 0.500000004740163, 1.0000000379432996, 1.0]
    .map((c) => `(local.set $e ${madd('(local.get $e)', '(local.get $x)', vconst(c))})`).join('\n  ')}
  (local.set $e (f32x4.mul (local.get $e) (i32x4.shl (f32x4.add (local.get $n) ${vconst(12583039)}) (i32.const 23))))`;

// Tile state offsets from the worker's scratch: planes T, D, F0, F1, F2 of 16 rows of 16 f32, each
// followed by 3 rows of padding, which rows done together reach beyond the tile (masked there).
const PLANE = 19 * 64;
const T = 0, D = PLANE, F0 = 2 * PLANE, F1 = 3 * PLANE, F2 = 4 * PLANE;
export const SCRATCH = 5 * PLANE;

// Per row i of the `rows` rows done together (i = 0, 1): dy, and the power's terms in dx: power = dx (A/2 dx + s1) + s2.
// Row i > 0 is masked ($valid_i) where it lies beyond the rectangle's last row.
const rowSetup = (rows) => Array.from({ length: rows }, (_, i) => `
      (local.set $dy (f32.sub (f32.add (f32.convert_i32_s (i32.add (local.get $y0) (i32.add (local.get $r) (i32.const ${i})))) (f32.const 0.5))
                              (local.get $my)))
      (local.set $s1_${i} (f32x4.splat (f32.mul (local.get $cb) (local.get $dy))))
      (local.set $s2_${i} (f32x4.splat (f32.mul (f32.mul (local.get $hc) (local.get $dy)) (local.get $dy))))
      ${i ? `(local.set $valid_${i} (i32x4.splat (i32.sub (i32.const 0) (i32.le_s (i32.add (local.get $r) (i32.const ${i})) (local.get $vb)))))` : ''}`).join('');

// One group of 4 pixels of row i (state at $a + 64 i) and the Gaussian: the spec's rules, branch-free.
const blend = (i) => `
       (local.set $p ${madd('(local.get $dx)', `(f32x4.add (local.get $q) (local.get $s1_${i}))`, `(local.get $s2_${i})`)})
       ${expNeg()}
       (local.set $al (f32x4.pmin (f32x4.mul (local.get $vo) (local.get $e)) ${vconst(0.99)}))
       (local.set $t (v128.load offset=${T + 64 * i} (local.get $a)))
       (local.set $ok (v128.and (v128.and (local.get $inx) (f32x4.ge (local.get $al) ${vconst('0x1.010102p-8')}))
                                (v128.and (f32x4.gt (local.get $t) (v128.const i32x4 0 0 0 0)) (f32x4.ge (local.get $p) (v128.const i32x4 0 0 0 0)))))
       ${i ? `(local.set $ok (v128.and (local.get $ok) (local.get $valid_${i})))` : ''}
       (local.set $tn (f32x4.mul (local.get $t) (f32x4.sub ${vconst(1)} (local.get $al))))
       (local.set $stop (v128.and (local.get $ok) (f32x4.lt (local.get $tn) ${vconst('0x1.a36e3p-14')})))
       (local.set $add (v128.andnot (local.get $ok) (local.get $stop)))
       (local.set $w (v128.and (f32x4.mul (local.get $al) (local.get $t)) (local.get $add)))
       (v128.store offset=${T + 64 * i} (local.get $a)
         (v128.bitselect (local.get $tn) (v128.xor (local.get $t) (v128.and (local.get $stop) ${vconst('-0.0')})) (local.get $add)))
       ${[[D, '$vz'], [F0, '$vf0'], [F1, '$vf1'], [F2, '$vf2']].map(([plane, v]) => `(v128.store offset=${plane + 64 * i} (local.get $a)
         ${madd('(local.get $w)', `(local.get ${v})`, `(v128.load offset=${plane + 64 * i} (local.get $a))`)})`).join('\n       ')}
       (if (v128.any_true (local.get $stop)) (then
        (local.set $live (i32.sub (local.get $live) (i32.popcnt (i32x4.bitmask (local.get $stop)))))))`;

// The module's text; rows: how many rows of a Gaussian's rectangle are composited together (1 to 4).
export function wat({ rows = 2, fma = false } = {}) {
  CONSTS.clear();
  FMA = fma;
  const text = `(module
 (memory (import "env" "mem") 1 65536 shared)
 (func (export "composite") (param $rec i32) (param $tstart i32) (param $tids i32) (param $torder i32)
   (param $ntiles i32) (param $counter i32) (param $tilesx i32) (param $width i32) (param $height i32)
   (param $outf i32) (param $outa i32) (param $outd i32) (param $scr i32)
   (local $i i32) (local $tile i32) (local $x0 i32) (local $y0 i32) (local $x1 i32) (local $y1 i32)
   (local $ncols i32) (local $nrows i32) (local $live i32) (local $k i32) (local $kend i32) (local $g i32)
   (local $b i32) (local $ua i32) (local $ub i32) (local $vt i32) (local $vb i32)
   (local $r i32) (local $gi i32) (local $gend i32) (local $a i32) (local $j i32) (local $o i32)
   (local $my f32) (local $cb f32) (local $hc f32) (local $dy f32) (local $alpha f32)
   (local $vmx v128) (local $vha v128) (local $vo v128) (local $vz v128) (local $vf0 v128) (local $vf1 v128)
   (local $vf2 v128) (local $left v128) (local $right v128) (local $px v128)
   (local $dx v128) (local $p v128) (local $x v128) (local $n v128) (local $e v128) (local $al v128) (local $t v128)
   (local $tn v128) (local $ok v128) (local $stop v128) (local $add v128) (local $w v128)
   (local $q v128) (local $inx v128) ${[0, 1, 2, 3].map((i) => `(local $s1_${i} v128) (local $s2_${i} v128) (local $valid_${i} v128)`).join(' ')}
   ;;CONST_LOCALS
   ;;CONST_INITS
   (block $done (loop $tiles
    (local.set $i (i32.atomic.rmw.add (local.get $counter) (i32.const 1)))
    (br_if $done (i32.ge_u (local.get $i) (local.get $ntiles)))
    (local.set $tile (i32.load (i32.add (local.get $torder) (i32.shl (local.get $i) (i32.const 2)))))
    (local.set $x0 (i32.shl (i32.rem_u (local.get $tile) (local.get $tilesx)) (i32.const 4)))
    (local.set $y0 (i32.shl (i32.div_u (local.get $tile) (local.get $tilesx)) (i32.const 4)))
    (local.set $ncols (i32.sub (local.get $width) (local.get $x0)))
    (if (i32.gt_s (local.get $ncols) (i32.const 16)) (then (local.set $ncols (i32.const 16))))
    (local.set $nrows (i32.sub (local.get $height) (local.get $y0)))
    (if (i32.gt_s (local.get $nrows) (i32.const 16)) (then (local.set $nrows (i32.const 16))))
    (local.set $x1 (i32.sub (i32.add (local.get $x0) (local.get $ncols)) (i32.const 1)))
    (local.set $y1 (i32.sub (i32.add (local.get $y0) (local.get $nrows)) (i32.const 1)))
    (local.set $live (i32.mul (local.get $ncols) (local.get $nrows)))
    ;; clear the tile's state
    (local.set $j (i32.const 0))
    (loop $clear
     (local.set $a (i32.add (local.get $scr) (local.get $j)))
     (v128.store offset=${T} (local.get $a) ${vconst(1)})
     (v128.store offset=${D} (local.get $a) (v128.const i32x4 0 0 0 0))
     (v128.store offset=${F0} (local.get $a) (v128.const i32x4 0 0 0 0))
     (v128.store offset=${F1} (local.get $a) (v128.const i32x4 0 0 0 0))
     (v128.store offset=${F2} (local.get $a) (v128.const i32x4 0 0 0 0))
     (local.set $j (i32.add (local.get $j) (i32.const 16)))
     (br_if $clear (i32.lt_u (local.get $j) (i32.const 1024))))
    ;; the tile's list, front to back
    (local.set $k (i32.load (i32.add (local.get $tstart) (i32.shl (local.get $tile) (i32.const 2)))))
    (local.set $kend (i32.load offset=4 (i32.add (local.get $tstart) (i32.shl (local.get $tile) (i32.const 2)))))
    (block $tile_done (loop $list
     (br_if $tile_done (i32.ge_u (local.get $k) (local.get $kend)))
     (local.set $g (i32.load (i32.add (local.get $tids) (i32.shl (local.get $k) (i32.const 2)))))
     (local.set $b (i32.add (local.get $rec) (i32.shl (local.get $g) (i32.const 6))))
     (local.set $ua (i32.trunc_f32_s (f32.load offset=32 (local.get $b))))
     (if (i32.lt_s (local.get $ua) (local.get $x0)) (then (local.set $ua (local.get $x0))))
     (local.set $ub (i32.trunc_f32_s (f32.load offset=36 (local.get $b))))
     (if (i32.gt_s (local.get $ub) (local.get $x1)) (then (local.set $ub (local.get $x1))))
     (local.set $vt (i32.trunc_f32_s (f32.load offset=40 (local.get $b))))
     (if (i32.lt_s (local.get $vt) (local.get $y0)) (then (local.set $vt (local.get $y0))))
     (local.set $vb (i32.trunc_f32_s (f32.load offset=44 (local.get $b))))
     (if (i32.gt_s (local.get $vb) (local.get $y1)) (then (local.set $vb (local.get $y1))))
     (local.set $vt (i32.sub (local.get $vt) (local.get $y0)))
     (local.set $vb (i32.sub (local.get $vb) (local.get $y0)))
     (local.set $left (f32x4.splat (f32.add (f32.convert_i32_s (local.get $ua)) (f32.const 0.5))))
     (local.set $right (f32x4.splat (f32.add (f32.convert_i32_s (local.get $ub)) (f32.const 0.5))))
     (local.set $vmx (f32x4.splat (f32.load offset=0 (local.get $b))))
     (local.set $my (f32.load offset=4 (local.get $b)))
     (local.set $vha (f32x4.splat (f32.load offset=8 (local.get $b))))
     (local.set $cb (f32.load offset=12 (local.get $b)))
     (local.set $hc (f32.load offset=16 (local.get $b)))
     (local.set $vo (f32x4.splat (f32.load offset=20 (local.get $b))))
     (local.set $vz (f32x4.splat (f32.load offset=24 (local.get $b))))
     (local.set $vf0 (f32x4.splat (f32.load offset=48 (local.get $b))))
     (local.set $vf1 (f32x4.splat (f32.load offset=52 (local.get $b))))
     (local.set $vf2 (f32x4.splat (f32.load offset=56 (local.get $b))))
     (local.set $r (local.get $vt))
     (block $rect_done (loop $rect
      (br_if $rect_done (i32.gt_s (local.get $r) (local.get $vb)))
      ${rowSetup(rows)}
      (local.set $gi (i32.shr_u (i32.sub (local.get $ua) (local.get $x0)) (i32.const 2)))
      (local.set $gend (i32.shr_u (i32.sub (local.get $ub) (local.get $x0)) (i32.const 2)))
      (local.set $a (i32.add (local.get $scr) (i32.add (i32.shl (local.get $r) (i32.const 6)) (i32.shl (local.get $gi) (i32.const 4)))))
      (local.set $px (f32x4.add (f32x4.splat (f32.convert_i32_s (i32.add (local.get $x0) (i32.shl (local.get $gi) (i32.const 2)))))
                                (v128.const f32x4 0.5 1.5 2.5 3.5)))
      (loop $groups
       (local.set $dx (f32x4.sub (local.get $px) (local.get $vmx)))
       (local.set $q (f32x4.mul (local.get $vha) (local.get $dx)))
       (local.set $inx (v128.and (f32x4.ge (local.get $px) (local.get $left)) (f32x4.le (local.get $px) (local.get $right))))
       ${Array.from({ length: rows }, (_, i) => blend(i)).join('\n')}
       (local.set $px (f32x4.add (local.get $px) ${vconst(4)}))
       (local.set $a (i32.add (local.get $a) (i32.const 16)))
       (local.set $gi (i32.add (local.get $gi) (i32.const 1)))
       (br_if $groups (i32.le_u (local.get $gi) (local.get $gend))))
      (local.set $r (i32.add (local.get $r) (i32.const ${rows})))
      (br $rect)))
     (br_if $tile_done (i32.eqz (local.get $live)))
     (local.set $k (i32.add (local.get $k) (i32.const 1)))
     (br $list)))
    ;; write out: alpha = 1 - |T|, depth = D / alpha (0 where alpha = 0), features interleaved
    (local.set $r (i32.const 0))
    (loop $out_rows
     (local.set $j (i32.const 0))
     (loop $out_cols
      (local.set $a (i32.add (local.get $scr) (i32.shl (i32.add (i32.shl (local.get $r) (i32.const 4)) (local.get $j)) (i32.const 2))))
      (local.set $o (i32.add (i32.mul (i32.add (local.get $y0) (local.get $r)) (local.get $width)) (i32.add (local.get $x0) (local.get $j))))
      (local.set $alpha (f32.sub (f32.const 1) (f32.abs (f32.load offset=${T} (local.get $a)))))
      (f32.store (i32.add (local.get $outa) (i32.shl (local.get $o) (i32.const 2))) (local.get $alpha))
      (f32.store (i32.add (local.get $outd) (i32.shl (local.get $o) (i32.const 2)))
        (select (f32.div (f32.load offset=${D} (local.get $a)) (local.get $alpha)) (f32.const 0)
                (f32.gt (local.get $alpha) (f32.const 0))))
      (local.set $o (i32.add (local.get $outf) (i32.mul (local.get $o) (i32.const 12))))
      (f32.store offset=0 (local.get $o) (f32.load offset=${F0} (local.get $a)))
      (f32.store offset=4 (local.get $o) (f32.load offset=${F1} (local.get $a)))
      (f32.store offset=8 (local.get $o) (f32.load offset=${F2} (local.get $a)))
      (local.set $j (i32.add (local.get $j) (i32.const 1)))
      (br_if $out_cols (i32.lt_u (local.get $j) (local.get $ncols))))
     (local.set $r (i32.add (local.get $r) (i32.const 1)))
     (br_if $out_rows (i32.lt_u (local.get $r) (local.get $nrows))))
    (br $tiles)))))
`;
  return text.replace(';;CONST_LOCALS', constLocals()).replace(';;CONST_INITS', constInits());
}

// The rest of a page frame on the CPU, in plain JavaScript (one thread), for lite: what
// stg_runtime's time evaluation, splat_cpu._project (pinhole footprint, projection.footprint),
// sort_by_depth (LSD radix on the float32 depth; ties not refined) and bin_tiles do, into the
// compositor's inputs (records, tile lists in depth order, tiles longest list first). A bound on the
// cost, checked only by its counts against the dump.
export function makeFrontEnd(meta, seg) {
  const n = meta.gaussians, W = meta.width, H = meta.height, TS = meta.tile, tx = meta.tiles_x;
  const ty = Math.ceil(H / TS), nTiles = tx * ty, P = meta.position_terms, Q = meta.rotation_terms;
  const rec = new Float32Array(n * 16), rect = new Int32Array(n * 4), keys = new Uint32Array(n), ids = new Int32Array(n);
  const keys2 = new Uint32Array(n), ids2 = new Int32Array(n), depth = new Float32Array(1), depthBits = new Uint32Array(depth.buffer);
  const count = new Int32Array(2048), tileStart = new Int32Array(nTiles + 1), cursor = new Int32Array(nTiles);
  let tileIds = new Int32Array(1 << 20);
  const tileOrder = new Int32Array(nTiles);
  const c = meta.camera, NEAR = meta.near, BLUR = meta.blur, LOG255 = Math.log(255);
  return function frontEnd(tau) {
    let kept = 0;
    for (let i = 0; i < n; i++) {
      const d = Math.fround(tau - seg.t_center[i]);
      const o = Math.fround(seg.opacity[i] * Math.exp(-seg.t_scale[i] * d * d));
      if (!(o >= 1 / 255)) continue;
      const pb = i * P * 3;
      let wx = 0, wy = 0, wz = 0;
      for (let k = P - 1; k >= 0; k--) { wx = wx * d + seg.position[pb + 3 * k]; wy = wy * d + seg.position[pb + 3 * k + 1]; wz = wz * d + seg.position[pb + 3 * k + 2]; }
      const x = c[0] * wx + c[1] * wy + c[2] * wz + c[9], y = c[3] * wx + c[4] * wy + c[5] * wz + c[10];
      const z = c[6] * wx + c[7] * wy + c[8] * wz + c[11];
      if (!(z > NEAR)) continue;
      const rb = i * Q * 4;
      let qw = 0, qx = 0, qy = 0, qz = 0;
      for (let k = Q - 1; k >= 0; k--) { qw = qw * d + seg.rotation[rb + 4 * k]; qx = qx * d + seg.rotation[rb + 4 * k + 1]; qy = qy * d + seg.rotation[rb + 4 * k + 2]; qz = qz * d + seg.rotation[rb + 4 * k + 3]; }
      let qn = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
      if (qn > 0) { qn = 1 / qn; qw *= qn; qx *= qn; qy *= qn; qz *= qn; } else qw = 1;
      const R = [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
        2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
        2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)];
      const iz = 1 / z;
      const xz = Math.min(Math.max(x * iz, c[19]), c[20]), yz = Math.min(Math.max(y * iz, c[21]), c[22]);
      const j00 = c[12] * iz, j02 = -j00 * xz, j11 = c[13] * iz, j12 = -j11 * yz;
      const u = c[12] * x * iz + c[14], v = c[13] * y * iz + c[15];
      let a = BLUR, b = 0, cc = BLUR;
      for (let k = 0; k < 3; k++) {
        const s = seg.scale[3 * i + k], g0 = R[k], g1 = R[3 + k], g2 = R[6 + k];
        const m0 = (c[0] * g0 + c[1] * g1 + c[2] * g2) * s, m1 = (c[3] * g0 + c[4] * g1 + c[5] * g2) * s;
        const m2 = (c[6] * g0 + c[7] * g1 + c[8] * g2) * s;
        const t0 = j00 * m0 + j02 * m2, t1 = j11 * m1 + j12 * m2;
        a += t0 * t0; b += t0 * t1; cc += t1 * t1;
      }
      const det = a * cc - b * b;
      if (!(det > 0)) continue;
      const mid = 0.5 * (a + cc), spread = mid * mid - det;
      const r = Math.ceil(Math.min(3 * Math.sqrt(mid + Math.sqrt(Math.max(spread, 0.1))), 1e15));
      const thr = Math.log(Math.fround(255 * o)) + 0.01;
      const hx = Math.min(r, Math.sqrt(2 * thr * a)), hy = Math.min(r, Math.sqrt(2 * thr * cc));
      const u0 = Math.max(0, Math.ceil(Math.min(Math.max(u - hx - 0.5, -1), W))), u1 = Math.min(W - 1, Math.floor(Math.min(Math.max(u + hx - 0.5, -1), W)));
      const v0 = Math.max(0, Math.ceil(Math.min(Math.max(v - hy - 0.5, -1), H))), v1 = Math.min(H - 1, Math.floor(Math.min(Math.max(v + hy - 0.5, -1), H)));
      if (u0 > u1 || v0 > v1) continue;
      const idet = 1 / det, o16 = 16 * i;
      rec[o16] = u; rec[o16 + 1] = v; rec[o16 + 2] = 0.5 * cc * idet; rec[o16 + 3] = -b * idet; rec[o16 + 4] = 0.5 * a * idet;
      rec[o16 + 5] = o; rec[o16 + 6] = z; rec[o16 + 7] = thr; rec[o16 + 8] = u0; rec[o16 + 9] = u1; rec[o16 + 10] = v0; rec[o16 + 11] = v1;
      rec[o16 + 12] = seg.features[3 * i]; rec[o16 + 13] = seg.features[3 * i + 1]; rec[o16 + 14] = seg.features[3 * i + 2];
      rect[4 * i] = (u0 / TS) | 0; rect[4 * i + 1] = (u1 / TS) | 0; rect[4 * i + 2] = (v0 / TS) | 0; rect[4 * i + 3] = (v1 / TS) | 0;
      depth[0] = z; keys[kept] = depthBits[0]; ids[kept] = i; kept++;
    }
    // stable LSD radix sort on the float32 depth's bits (positive floats: monotonic), 3 x 11 bits
    let sk = keys, si = ids, dk = keys2, di = ids2;
    for (let shift = 0; shift < 33; shift += 11) {
      count.fill(0);
      for (let j = 0; j < kept; j++) count[(sk[j] >>> shift) & 2047]++;
      let total = 0;
      for (let q = 0; q < 2048; q++) { const t = count[q]; count[q] = total; total += t; }
      for (let j = 0; j < kept; j++) { const p = count[(sk[j] >>> shift) & 2047]++; dk[p] = sk[j]; di[p] = si[j]; }
      [sk, dk] = [dk, sk]; [si, di] = [di, si];
    }
    // tile lists in depth order: count, prefix sums, fill
    cursor.fill(0);
    for (let j = 0; j < kept; j++) {
      const g = 4 * si[j];
      for (let yy = rect[g + 2]; yy <= rect[g + 3]; yy++) for (let xx = rect[g]; xx <= rect[g + 1]; xx++) cursor[yy * tx + xx]++;
    }
    let total = 0;
    for (let t = 0; t < nTiles; t++) { tileStart[t] = total; total += cursor[t]; cursor[t] = tileStart[t]; }
    tileStart[nTiles] = total;
    if (tileIds.length < total) tileIds = new Int32Array(total * 1.25);
    for (let j = 0; j < kept; j++) {
      const id = si[j], g = 4 * id;
      for (let yy = rect[g + 2]; yy <= rect[g + 3]; yy++) for (let xx = rect[g]; xx <= rect[g + 1]; xx++) tileIds[cursor[yy * tx + xx]++] = id;
    }
    for (let t = 0; t < nTiles; t++) tileOrder[t] = t;
    tileOrder.sort((p, q) => (tileStart[q + 1] - tileStart[q]) - (tileStart[p + 1] - tileStart[p]));
    return { kept, entries: total };
  };
}

function assemble(options) {
  const require = createRequire(import.meta.url);
  const wabtModule = require(process.env.WABT || 'wabt');
  return wabtModule().then((wabt) => {
    const parsed = wabt.parseWat('probe.wat', wat(options), { simd: true, threads: true, relaxed_simd: true });
    const bytes = parsed.toBinary({}).buffer;
    parsed.destroy();
    return new WebAssembly.Module(bytes);
  });
}

// The frame's arrays laid out in one shared memory: byte offsets of each, 64-byte aligned.
function layout(dir) {
  const meta = JSON.parse(readFileSync(`${dir}/meta.json`, 'utf8'));
  const read = (name, Type) => { const b = readFileSync(`${dir}/${name}.bin`); return new Type(b.buffer, b.byteOffset, b.byteLength / 4); };
  const inputs = { rec: read('packed', Float32Array), tstart: read('tile_start', Int32Array), tids: read('tile_ids', Int32Array),
    torder: read('tile_order', Int32Array) };
  const seg = Object.fromEntries(['opacity', 't_center', 't_scale', 'position', 'rotation', 'scale', 'features']
    .map((name) => [name, read(`seg_${name}`, Float32Array)]));
  const refs = { f: read('ref_f', Float32Array), a: read('ref_a', Float32Array), d: read('ref_d', Float32Array) };
  const pixels = meta.width * meta.height;
  const at = {};
  let end = 64;  // 0..63: the tile counter
  const place = (name, bytes) => { at[name] = end; end += Math.ceil(bytes / 64) * 64; };
  for (const [name, a] of Object.entries(inputs)) place(name, a.byteLength);
  place('outf', pixels * 12); place('outa', pixels * 4); place('outd', pixels * 4);
  place('scr0', SCRATCH); place('scr1', SCRATCH);
  const pages = Math.ceil(end / 65536);
  return { meta, inputs, refs, at, pages, seg };
}

function instance(module, memory) {
  return new WebAssembly.Instance(module, { env: { mem: memory } }).exports.composite;
}

function run(composite, memory, L, scr) {
  const { at, meta } = L;
  composite(at.rec, at.tstart, at.tids, at.torder, L.inputs.torder.length, 0, meta.tiles_x, meta.width, meta.height,
    at.outf, at.outa, at.outd, at[scr]);
}

if (!isMainThread) {  // a compositing worker: one call per message, on the shared memory
  const { modules, memory, L, scr } = workerData;
  const kernels = Object.fromEntries(Object.entries(modules).map(([name, m]) => [name, instance(m, memory)]));
  parentPort.on('message', (m) => {
    if (typeof m === 'string') { run(kernels[m], memory, L, scr); parentPort.postMessage('done'); }
    else parentPort.postMessage(m.records.length + m.tids.length);  // a copy arrived ("copy")
  });
} else {
  const serve = process.argv[2] === '--serve';
  const dir = process.argv[serve ? 3 : 2] || '/tmp/stg-wasm-probe';
  const L = layout(dir);
  // simd: standard SIMD (node 20, every browser with WASM SIMD); fma: relaxed SIMD's relaxed_madd
  // (Chromium 114+ by default; node 20 with --experimental-wasm-relaxed-simd), where available.
  const modules = { simd: await assemble({ rows: 2 }) };
  try { modules.fma = await assemble({ rows: 2, fma: true }); } catch { /* no relaxed SIMD here */ }
  const memory = new WebAssembly.Memory({ initial: L.pages, maximum: L.pages, shared: true });
  for (const [name, a] of Object.entries(L.inputs)) new a.constructor(memory.buffer, L.at[name], a.length).set(a);
  const counter = new Int32Array(memory.buffer, 0, 1);
  const kernels = Object.fromEntries(Object.entries(modules).map(([name, m]) => [name, instance(m, memory)]));
  const workers = ['scr0', 'scr1'].map((scr) => new Worker(new URL(import.meta.url), { workerData: { modules, memory, scr,
    L: { at: L.at, meta: L.meta, inputs: { torder: { length: L.inputs.torder.length } } } } }));
  const reply = (w) => new Promise((ok) => w.once('message', ok));
  const pixels = L.meta.width * L.meta.height;
  const outputs = () => ({ f: new Float32Array(memory.buffer, L.at.outf, pixels * 3).slice(),
    a: new Float32Array(memory.buffer, L.at.outa, pixels).slice(), d: new Float32Array(memory.buffer, L.at.outd, pixels).slice() });

  const frontEnd = makeFrontEnd(L.meta, L.seg);
  const front = () => { const t0 = performance.now(); frontEnd(L.meta.tau); return performance.now() - t0; };
  const c1 = (kind) => { counter[0] = 0; const t0 = performance.now(); run(kernels[kind], memory, L, 'scr0'); return performance.now() - t0; };
  const c2 = async (kind) => {
    counter[0] = 0; const t0 = performance.now();
    const done = workers.map(reply); workers.forEach((w) => w.postMessage(kind)); await Promise.all(done);
    return performance.now() - t0;
  };
  const image = new Uint8Array(pixels * 4);
  const copy = async () => {  // the records and lists to a worker (structured clone: a copy), an RGBA image back
    const t0 = performance.now();
    const got = reply(workers[1]);
    workers[1].postMessage({ records: L.inputs.rec, tids: L.inputs.tids });
    await got;
    await new Promise((ok) => {
      const { port1, port2 } = new MessageChannel();
      port2.once('message', (m) => { port1.close(); port2.close(); ok(m); });
      port1.postMessage(image);
    });
    return performance.now() - t0;
  };
  const compare = (out) => {
    const diff = (x, y) => { let m = 0; for (let i = 0; i < x.length; i++) m = Math.max(m, Math.abs(x[i] - y[i])); return m; };
    let se = 0; for (let i = 0; i < out.f.length; i++) se += (out.f[i] - L.refs.f[i]) ** 2;
    const psnr = 10 * Math.log10(1 / (se / out.f.length));
    return `max |diff| features ${diff(out.f, L.refs.f).toExponential(2)}, alpha ${diff(out.a, L.refs.a).toExponential(2)}, `
      + `depth ${diff(out.d, L.refs.d).toExponential(2)}, features PSNR ${psnr.toFixed(1)} dB (peak 1)`;
  };
  const check = async () => {
    const lines = [];
    for (const kind of Object.keys(kernels)) {
      c1(kind); const one = outputs(); await c2(kind); const two = outputs();
      const same = two.f.every((v, i) => v === one.f[i]) && two.a.every((v, i) => v === one.a[i]) && two.d.every((v, i) => v === one.d[i]);
      const close = ['f', 'a', 'd'].every((c) => one[c].every((v, i) => Math.abs(v - L.refs[c][i]) < 1e-3));
      lines.push(`${close && same ? '' : 'FAIL '}${kind}: ${compare(one)}; 2 workers: ${same ? 'the same bits' : 'DIFFERENT'}`);
    }
    const { kept, entries } = frontEnd(L.meta.tau);
    return `${lines.join('; ')}; ${entries === L.meta.entries ? '' : 'FAIL '}JS front end: ${kept} Gaussians projected, `
      + `${entries} tile-list entries (numba: ${L.meta.entries})`;
  };
  const commands = { check, front, copy, kinds: () => Object.keys(kernels).join(' '),
    ...Object.fromEntries(Object.keys(kernels).flatMap((k) => [[`c1 ${k}`, () => c1(k)], [`c2 ${k}`, () => c2(k)]])) };

  if (serve) {
    const { createInterface } = await import('node:readline');
    for await (const line of createInterface({ input: process.stdin })) {
      const command = commands[line.trim()];
      const answer = command ? await command() : `? ${line.trim()}`;
      process.stdout.write(`${typeof answer === 'number' ? answer.toFixed(3) : answer}\n`);
    }
  } else {  // alone: the check, then 12 rounds of each timing, interleaved
    console.log(await check());
    const names = Object.keys(commands).filter((c) => c !== 'check' && c !== 'kinds');
    const times = Object.fromEntries(names.map((c) => [c, []]));
    for (let i = 0; i < 12; i++) for (const c of names) times[c].push(await commands[c]());
    for (const c of names) {
      const xs = times[c].sort((a, b) => a - b);
      console.log(`${c.padEnd(8)} min ${xs[0].toFixed(2)} median ${xs[xs.length >> 1].toFixed(2)} ms`);
    }
  }
  workers.forEach((w) => w.terminate());
}
