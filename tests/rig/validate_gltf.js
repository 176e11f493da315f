// Validate a .glb with the Khronos glTF validator (npm gltf-validator); prints its JSON report.
// usage: NODE_PATH="$(npm root -g)" node validate_gltf.js FILE.glb
const fs = require('fs');
const validator = require('gltf-validator');
const data = new Uint8Array(fs.readFileSync(process.argv[2]));
validator.validateBytes(data, {maxIssues: 100, writeTimestamp: false})
  .then((report) => { console.log(JSON.stringify(report)); })
  .catch((error) => { console.error('validation failed: ' + error); process.exit(1); });
