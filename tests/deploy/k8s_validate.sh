#!/usr/bin/env bash
# The ctest k8s_manifests: installs the pinned kubernetes-models (tests/deploy/package-lock.json)
# with `npm ci` into WORK_DIR and schema-checks every document of deploy/k8s/*.yaml with
# deploy/k8s/validate.js (the Kubernetes API's OpenAPI schemas, offline). It first checks that the
# validator refuses a manifest with a wrong field type, so a validator that accepts everything
# fails the test instead of passing it.
#   tests/deploy/k8s_validate.sh SOURCE_DIR WORK_DIR
set -euo pipefail
src=$1
work=$2
mkdir -p "$work"
cp "$src/tests/deploy/package.json" "$src/tests/deploy/package-lock.json" "$work/"
# npm's own cache makes a repeated install offline; no install scripts run.
npm ci --prefix "$work" --no-audit --no-fund --ignore-scripts --prefer-offline --loglevel=error
export NODE_PATH="$work/node_modules"
cat > "$work/bad.yaml" <<'YAML'
apiVersion: v1
kind: Service
metadata:
  name: bad
spec:
  ports:
    - port: "not a number"
YAML
if node "$src/deploy/k8s/validate.js" "$work/bad.yaml" > "$work/bad.out" 2>&1; then
    echo "k8s_manifests: the validator accepted a Service whose port is a string:" >&2
    cat "$work/bad.out" >&2
    exit 1
fi
node "$src/deploy/k8s/validate.js" "$src/deploy/k8s/kdrt.yaml" "$src/deploy/k8s/configmaps.yaml"
