#!/usr/bin/env bash
# Renders a run's report.html in headless Chromium (Debian's package) and saves a screenshot,
# so a person can check the page as a browser shows it.
# Usage: scripts/report_screenshot.sh RUN_DIR [OUT.png]
set -euo pipefail
run=${1:?usage: scripts/report_screenshot.sh RUN_DIR [OUT.png]}
out=${2:-$run/report.png}
[ -f "$run/report.html" ] || { echo "no $run/report.html: run 'nanoeye run --out $run' first" >&2; exit 1; }
if ! command -v chromium >/dev/null 2>&1; then
  echo "installing Debian's chromium (needs root)" >&2
  apt-get update -qq && apt-get install -y -qq chromium >/dev/null
fi
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
  --disable-background-networking --disable-component-update --disable-sync \
  --user-data-dir="$profile" --window-size=1200,3000 \
  --screenshot="$(realpath -m "$out")" "file://$(realpath "$run/report.html")" 2>/dev/null
echo "$out"
