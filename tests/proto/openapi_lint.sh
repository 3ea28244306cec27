#!/usr/bin/env bash
# The ctest openapi_lint: installs the pinned Redocly CLI (tests/proto/openapi_lint/package-lock.json)
# with `npm ci` into WORK_DIR and lints proto/openapi.yaml with proto/redocly.yaml (every rule of the
# strict set an error). Exits non-zero on any problem the linter reports.
#   tests/proto/openapi_lint.sh SOURCE_DIR WORK_DIR
set -euo pipefail
src=$1
work=$2
mkdir -p "$work"
cp "$src/tests/proto/openapi_lint/package.json" "$src/tests/proto/openapi_lint/package-lock.json" "$work/"
# npm's own cache makes a repeated install offline; no install scripts run.
npm ci --prefix "$work" --no-audit --no-fund --ignore-scripts --prefer-offline --loglevel=error
export REDOCLY_TELEMETRY=off REDOCLY_SUPPRESS_UPDATE_NOTICE=true NO_COLOR=1
"$work/node_modules/.bin/redocly" lint --config "$src/proto/redocly.yaml" "$src/proto/openapi.yaml"
