// Schema-checks Kubernetes manifests offline with the npm package kubernetes-models (its
// validate() runs the API's OpenAPI schemas with ajv). The ctest k8s_manifests runs it
// (tests/deploy/k8s_validate.sh, with the packages of tests/deploy/package-lock.json). By hand:
//   npm ci --prefix /tmp/k8sval (after copying tests/deploy/package*.json there)
//   NODE_PATH=/tmp/k8sval/node_modules node deploy/k8s/validate.js deploy/k8s/*.yaml
// The packages are loaded with import(), not require(): kubernetes-models ships ES modules,
// which Node 18 (Debian 12's) refuses to require() (ERR_REQUIRE_ESM); import() takes both kinds.
const fs = require('fs');
const path = require('path');
const { pathToFileURL } = require('url');
const modules = (process.env.NODE_PATH || 'node_modules').split(':')[0];

/// The export `name` of the module at `file` (under `modules`): a named export of an ES module,
/// or a member of a CommonJS module's exports.
async function load(file, name) {
  const module = await import(pathToFileURL(path.join(modules, file)).href);
  const found = name === undefined ? (module.default ?? module) : (module[name] ?? module.default?.[name]);
  if (found === undefined) throw new Error(`${file} has no export ${name}`);
  return found;
}

async function main() {
  const yaml = await load('js-yaml/index.js');
  const models = {
    'v1/PersistentVolumeClaim': await load('kubernetes-models/v1/PersistentVolumeClaim.js', 'PersistentVolumeClaim'),
    'v1/Service': await load('kubernetes-models/v1/Service.js', 'Service'),
    'v1/ConfigMap': await load('kubernetes-models/v1/ConfigMap.js', 'ConfigMap'),
    'apps/v1/StatefulSet': await load('kubernetes-models/apps/v1/StatefulSet.js', 'StatefulSet'),
    'apps/v1/Deployment': await load('kubernetes-models/apps/v1/Deployment.js', 'Deployment'),
  };
  let bad = 0;
  for (const file of process.argv.slice(2)) {
    for (const doc of yaml.loadAll(fs.readFileSync(file, 'utf8'))) {
      const M = models[`${doc.apiVersion}/${doc.kind}`];
      if (!M) { console.log(`${file}: no model for ${doc.apiVersion}/${doc.kind}`); bad++; continue; }
      try { new M(doc).validate(); console.log(`ok ${doc.kind}/${doc.metadata.name}`); }
      catch (e) { console.log(`${file}: ${doc.kind}/${doc.metadata.name}: ${e.message}`); bad++; }
    }
  }
  return bad;
}

main().then((bad) => process.exit(bad ? 1 : 0), (e) => { console.log(`validate.js: ${e.stack || e}`); process.exit(1); });
