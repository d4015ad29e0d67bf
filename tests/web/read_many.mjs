// node tests/web/read_many.mjs FILE...: read each file with the web player's reader; print one JSON line
// per file: {"file", "ok": true} or {"file", "ok": false, "type", "error"}.
import { readFileSync } from "node:fs";
import { basename } from "node:path";
import { readStg } from "../../stg_runtime/web/stg-format.js";

for (const file of process.argv.slice(2)) {
  try {
    await readStg(new Uint8Array(readFileSync(file)), basename(file));
    console.log(JSON.stringify({ file, ok: true }));
  } catch (e) {
    console.log(JSON.stringify({ file, ok: false, type: e.name, error: e.message }));
  }
}
