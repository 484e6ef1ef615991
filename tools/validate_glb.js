#!/usr/bin/env node
// Validate a .glb/.gltf with the Khronos glTF validator (installed by tools/install_test_deps.sh).
// Usage: node tools/validate_glb.js FILE   -> prints the report's issues as JSON on stdout;
// exit status 0 when there are no errors, 1 when there are, 2 when the validator is missing.
const fs = require('fs');
const path = require('path');
let validator;
try {
  validator = require(path.join(__dirname, 'node_modules', 'gltf-validator'));
} catch (e) {
  console.error('gltf-validator is not installed: run tools/install_test_deps.sh');
  process.exit(2);
}
const file = process.argv[2];
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), { maxIssues: 1000 })
  .then((report) => {
    console.log(JSON.stringify({ validatorVersion: report.validatorVersion, issues: report.issues, info: report.info }));
    process.exit(report.issues.numErrors > 0 ? 1 : 0);
  })
  .catch((err) => { console.error(String(err)); process.exit(1); });
