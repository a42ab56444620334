// Runs the Khronos glTF Validator (npm gltf-validator, installed by `npm ci --prefix tools`)
// on the GLB files given as arguments; prints one JSON report per file, in order:
// {"file", "errors", "warnings", "infos", "messages": [{"code", "severity", "message", "pointer"}]}.
import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const tools = join(dirname(fileURLToPath(import.meta.url)), "..", "tools", "package.json");
const validator = createRequire(tools)("gltf-validator");

const reports = [];
for (const file of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, {
    uri: file,
    format: "glb",
    maxIssues: 100,
    externalResourceFunction: () => Promise.reject(new Error("no external resources expected")),
  });
  const issues = report.issues;
  reports.push({
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    messages: issues.messages.map(({ code, severity, message, pointer }) => ({ code, severity, message, pointer })),
  });
}
process.stdout.write(JSON.stringify(reports) + "\n");
