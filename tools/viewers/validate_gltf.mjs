// Validate glTF/GLB files with the Khronos glTF validator.
// Usage: node validate_gltf.mjs FILE.glb [FILE2.glb ...]
// Prints one JSON line per file: {file, errors, warnings, infos, messages:[first 20 issues]}.
// Exit code 1 when any file has errors.
import { readFile } from "node:fs/promises";
import path from "node:path";
import validator from "gltf-validator";

let failed = false;
for (const file of process.argv.slice(2)) {
  const data = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(data, {
    uri: path.basename(file),
    maxIssues: 0,
    externalResourceFunction: (uri) =>
      readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
  });
  const issues = report.issues;
  const out = {
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    messages: issues.messages.slice(0, 20).map((m) => `${m.severity} ${m.code} ${m.pointer ?? ""} ${m.message}`),
  };
  if (issues.numErrors > 0) failed = true;
  console.log(JSON.stringify(out));
}
process.exit(failed ? 1 : 0);
