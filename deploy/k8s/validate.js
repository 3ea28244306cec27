// Schema-checks Kubernetes manifests offline with the npm package kubernetes-models (its
// validate() runs the API's OpenAPI schemas with ajv). The ctest k8s_manifests runs it
// (tests/deploy/k8s_validate.sh, with the packages of tests/deploy/package-lock.json). By hand:
//   npm ci --prefix /tmp/k8sval (after copying tests/deploy/package*.json there)
//   NODE_PATH=/tmp/k8sval/node_modules node deploy/k8s/validate.js deploy/k8s/*.yaml
const fs = require('fs');
const path = require('path');
const modules = (process.env.NODE_PATH || 'node_modules').split(':')[0];
const yaml = require(path.join(modules, 'js-yaml'));
const models = {
  'v1/PersistentVolumeClaim': require(path.join(modules, 'kubernetes-models/v1/PersistentVolumeClaim.js')).PersistentVolumeClaim,
  'v1/Service': require(path.join(modules, 'kubernetes-models/v1/Service.js')).Service,
  'v1/ConfigMap': require(path.join(modules, 'kubernetes-models/v1/ConfigMap.js')).ConfigMap,
  'apps/v1/StatefulSet': require(path.join(modules, 'kubernetes-models/apps/v1/StatefulSet.js')).StatefulSet,
  'apps/v1/Deployment': require(path.join(modules, 'kubernetes-models/apps/v1/Deployment.js')).Deployment,
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
process.exit(bad ? 1 : 0);
