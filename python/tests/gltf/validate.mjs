// `node validate.mjs ASSET.gltf`: the Khronos glTF validator's report on ASSET (its external
// buffers and images read from beside it) as JSON on stdout.
import { readFile } from "node:fs/promises";
import { dirname, join } from "node:path";
import validator from "gltf-validator";

const path = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(await readFile(path)), {
  uri: path,
  maxIssues: 0,
  externalResourceFunction: (uri) =>
    readFile(join(dirname(path), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
});
process.stdout.write(JSON.stringify(report, null, 1));
