#!/usr/bin/env bash
# The contract checked like a public API: `buf lint` (proto/buf.yaml lists the exceptions the
# published names need, with why) and `buf breaking` against the contract as it last stood.
#
# The baseline: BUF_AGAINST (a git ref) when given; else HEAD when proto/ has uncommitted changes
# (the change being made); else the commit before the last one that changed proto/ (so a clean
# clone of main checks main's latest change of the contract). buf comes from the npm registry
# (@bufbuild/buf, pinned in tools/buf/package-lock.json), not from a download of its own.
set -euo pipefail
cd "$(dirname "$0")/.."

BUF=tools/buf/node_modules/.bin/buf
if [ ! -x "$BUF" ]; then
  npm ci --prefix tools/buf --no-audit --no-fund --silent
fi

(cd proto && "../$BUF" lint)
echo "buf lint: ok"

if [ -n "${BUF_AGAINST:-}" ]; then
  against=$BUF_AGAINST
elif ! git diff --quiet HEAD -- proto/; then
  against=$(git rev-parse HEAD)
else
  last=$(git log -1 --format=%H -- proto/)
  against=$(git rev-parse "$last^")
fi
"$BUF" breaking proto --against ".git#ref=$against,subdir=proto"
echo "buf breaking: ok against $against"
