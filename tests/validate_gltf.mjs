// Runs the Khronos glTF validator (npm gltf-validator, installed under tools/ by the Makefile)
// on one .glb/.gltf file and prints its JSON report on stdout.
//   node tests/validate_gltf.mjs FILE
// Exit status: 0 when the report has no errors, 1 when it has, 2 when the file could not be read.
import { createRequire } from "node:module";
import { readFileSync } from "node:fs";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const require = createRequire(path.join(here, "..", "tools", "package.json"));
const validator = require("gltf-validator");

const file = process.argv[2];
if (!file) {
  console.error("usage: node tests/validate_gltf.mjs FILE");
  process.exit(2);
}
let bytes;
try {
  bytes = new Uint8Array(readFileSync(file));
} catch (err) {
  console.error(`${file}: ${err.message}`);
  process.exit(2);
}
const report = await validator.validateBytes(bytes, { uri: path.basename(file), maxIssues: 1000 });
process.stdout.write(JSON.stringify(report));
process.exit(report.issues.numErrors === 0 ? 0 : 1);
