#!/usr/bin/env bash
# The ctest openapi_lint: installs the pinned Redocly CLI (tests/proto/openapi_lint/package-lock.json)
# with `npm ci` into WORK_DIR and lints proto/openapi.yaml with proto/redocly.yaml (every rule of the
# strict set an error). Exits non-zero on any problem the linter reports.
#   tests/proto/openapi_lint.sh SOURCE_DIR WORK_DIR
set -euo pipefail
src=$1
work=$2
# Redocly CLI needs node >= 20.19. Debian 12's own nodejs is 18: there the test reports itself
# skipped (exit 77, ctest's SKIP_RETURN_CODE) and says why, rather than failing or passing.
IFS=. read -r major minor _ <<< "$(node --version | tr -d v)"
if (( major < 20 || (major == 20 && minor < 19) )); then
    echo "openapi_lint: node $(node --version) is older than 20.19, which Redocly CLI needs: skipped"
    exit 77
fi
mkdir -p "$work"
cp "$src/tests/proto/openapi_lint/package.json" "$src/tests/proto/openapi_lint/package-lock.json" "$work/"
# npm's own cache makes a repeated install offline; no install scripts run.
npm ci --prefix "$work" --no-audit --no-fund --ignore-scripts --prefer-offline --loglevel=error
export REDOCLY_TELEMETRY=off REDOCLY_SUPPRESS_UPDATE_NOTICE=true NO_COLOR=1
"$work/node_modules/.bin/redocly" lint --config "$src/proto/redocly.yaml" "$src/proto/openapi.yaml"
