// Long videos over HTTP range requests (formats/stg-v1.md files, unchanged): the prefix and header
// first, then each segment's bytes when playback needs them (the segment at the playhead and the one
// after it). The file's SHA-256 covers every byte, so it is checked once every byte has arrived; until
// then each segment is guarded by the reader's own checks (the header's Limits against the file's
// size, blob bounds, sizes, zlib ends, (1.5) arithmetic-coded streams' ends, finite values, the
// decoder's MLP family).
//
//   openRanged(url, name, limits) -> {model, whole: Uint8Array} (the server sent the whole file, or the
//       file has one segment) or {model, file: RangedFile} (segments to fetch with file.segment(i))

import { FormatError, PREFIX_SIZE, decodeSegment, parseHeader, readPrefix, readStg, verifyChecksum } from "./stg-format.js";

const FIRST_BYTES = 65536;

function concat(parts, total) {
  const out = new Uint8Array(total ?? parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) { out.set(p, at); at += p.length; }
  return out;
}

async function fetchRange(url, start, end, name) {  // bytes [start, end)
  const response = await fetch(url, { headers: { Range: `bytes=${start}-${end - 1}` } });
  if (response.status !== 206) throw new FormatError(`${name}: the server stopped serving byte ranges (HTTP ${response.status})`);
  const bytes = new Uint8Array(await response.arrayBuffer());
  if (bytes.length !== end - start) throw new FormatError(`${name}: the server sent ${bytes.length} bytes for a range of ${end - start}`);
  return bytes;
}

function blobsOf(entry) {  // [offset, end) of every blob a segment entry names (valid-looking ones)
  const out = [];
  const add = (blob) => {
    if (blob && Number.isInteger(blob.offset) && Number.isInteger(blob.length) && blob.offset >= 0 && blob.length >= 0) {
      out.push([blob.offset, blob.offset + blob.length]);
    }
  };
  const walk = (a) => {  // an array's blob, its codebook's and its parts' (format 1.4; acB's are data blobs too)
    if (!a || typeof a !== "object") return;
    add(a.data);
    walk(a.codebook);
    if (Array.isArray(a.parts)) a.parts.forEach(walk);
  };
  Object.values(entry.attributes || {}).forEach(walk);
  if (entry.decoder) add(entry.decoder.data);
  return out;
}

/** A file read in pieces: bytes [0, first.length) at first, the rest in chunks at segment boundaries. */
export class RangedFile {
  constructor(url, name, model, first, headerLength) {
    this.url = url;
    this.name = name;
    this.model = model;
    this.total = model.fileSize;
    this.dataStart = PREFIX_SIZE + headerLength;
    this.pieces = new Map([[0, first]]);  // start -> bytes
    this.fetches = new Map();              // chunk index -> Promise
    const sectionLength = this.total - 32 - this.dataStart;
    this.section = { length: sectionLength, bytes: (offset, n) => this.read(this.dataStart + offset, n) };
    // segment i's bytes: from its first blob to the next segment's first blob (the last: to the end)
    this.needs = model.segments.map((s) => {
      const blobs = blobsOf(s.entry);
      if (!blobs.length) return [0, 0];
      const lo = Math.min(...blobs.map((b) => b[0])), hi = Math.max(...blobs.map((b) => b[1]));
      return [this.dataStart + Math.min(lo, sectionLength), this.dataStart + Math.min(hi, sectionLength)];
    });
    const cuts = new Set([first.length, this.total]);
    for (const [lo] of this.needs) if (lo > first.length && lo < this.total) cuts.add(lo);
    this.bounds = [...cuts].sort((a, b) => a - b);  // chunk j = [bounds[j], bounds[j + 1])
    this.checked = false;
    this.sentBytes = first.length;
  }

  read(start, n) {
    const parts = [];
    let at = start;
    const end = start + n;
    while (at < end) {
      let found = null;
      for (const [s, bytes] of this.pieces) if (s <= at && at < s + bytes.length) { found = [s, bytes]; break; }
      if (!found) throw new Error(`bytes ${at}.. of the file have not arrived`);
      const [s, bytes] = found, take = Math.min(end, s + bytes.length) - at;
      parts.push(bytes.subarray(at - s, at - s + take));
      at += take;
    }
    return parts.length === 1 ? parts[0] : concat(parts, n);
  }

  chunk(j) {
    if (!this.fetches.has(j)) {
      const [start, end] = [this.bounds[j], this.bounds[j + 1]];
      this.fetches.set(j, fetchRange(this.url, start, end, this.name).then((bytes) => {
        this.pieces.set(start, bytes);
        this.sentBytes += bytes.length;
      }));
    }
    return this.fetches.get(j);
  }

  /** Fetch (once) and decode segment i; then, when every byte has arrived, check the checksum. */
  async segment(i) {
    const [lo, hi] = this.needs[i];
    const waits = [];
    for (let j = 0; j + 1 < this.bounds.length; j++) {
      if (this.bounds[j] < Math.max(hi, lo + 1) && this.bounds[j + 1] > lo) waits.push(this.chunk(j));
    }
    await Promise.all(waits);
    const decoded = await decodeSegment(this.model, i, this.section);
    await this.checkWhenComplete();
    return decoded;
  }

  async checkWhenComplete() {
    if (this.checked || this.fetches.size + 1 < this.bounds.length) return;
    await Promise.all(this.fetches.values());
    if (this.checked) return;
    this.checked = true;
    const whole = this.read(0, this.total);
    try {
      await verifyChecksum(whole);
    } catch (e) {
      throw new FormatError(`${this.name}: ${e.message}`);
    }
  }

  /** Forget segment i's decoded arrays (they are decoded again from the bytes kept when needed). */
  release(i) { this.model.segments[i].decoded = null; }
}

/** Open `url`: by range requests when the server serves them and the file has several segments. */
export async function openRanged(url, name, limits) {
  const response = await fetch(url, { headers: { Range: `bytes=0-${FIRST_BYTES - 1}` } });
  if (!response.ok) throw new FormatError(`${name}: HTTP ${response.status} ${response.statusText}`);
  const first = new Uint8Array(await response.arrayBuffer());
  const total = response.status === 206 ? Number((response.headers.get("Content-Range") || "").split("/")[1]) : NaN;
  if (response.status !== 206 || !Number.isInteger(total) || first.length >= total) {
    const whole = first;  // 200: the server sent the whole file (or the range held all of it)
    return { model: await readStg(whole, name, limits), whole, sentBytes: whole.length };
  }
  let prefix;
  try {
    prefix = readPrefix(first);
    if (total < PREFIX_SIZE + prefix.headerLength + 32) {
      throw new Error(`truncated: header says ${prefix.headerLength} header bytes, file has ${total} bytes in all`);
    }
  } catch (e) {
    throw new FormatError(`${name}: ${e.message}`);
  }
  const headerEnd = PREFIX_SIZE + prefix.headerLength;
  const head = headerEnd <= first.length ? first : concat([first, await fetchRange(url, first.length, headerEnd, name)]);
  const model = parseHeader(head.subarray(PREFIX_SIZE, headerEnd), total, name, limits);
  if (model.segments.length === 1) {  // nothing to gain: the rest, then the whole file's checks first
    const whole = concat([head, await fetchRange(url, head.length, total, name)], total);
    return { model: await readStg(whole, name, limits), whole, sentBytes: total };
  }
  const file = new RangedFile(url, name, model, head, prefix.headerLength);
  return { model, file };
}
