// The Khronos glTF validator on GLB files: one JSON line per file with its issue counts and
// messages.   node web/validate.mjs a.glb [b.glb ...]
import { readFile } from 'node:fs/promises';
import validator from 'gltf-validator';

let failed = false;
for (const path of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(path));
  const report = await validator.validateBytes(bytes, { uri: path, maxIssues: 100 });
  const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
  failed ||= numErrors > 0;
  console.log(JSON.stringify({ path, numErrors, numWarnings, numInfos, numHints,
                               messages: messages.map(m => `${m.code} ${m.pointer || ''}: ${m.message}`),
                               extensionsUsed: report.info.extensionsUsed || [] }));
}
process.exit(failed ? 1 : 0);
