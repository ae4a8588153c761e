#!/usr/bin/env bash
# Rebuilds docs/benchmarks.md from docs/bench/summary.md and the per-crate sections.
set -euo pipefail
cd "$(dirname "$0")"
tmp=$(mktemp ../benchmarks.md.XXXXXX)
{
  cat summary.md
  for s in gaze renderer optics chain sensor fisher nets metalib mpi; do
    [ -f "$s.md" ] || continue
    printf '\n---\n\n'
    # Demote each section's headings one level under the summary's title.
    sed -e 's/^#/##/' "$s.md"
  done
} > "$tmp"
mv "$tmp" ../benchmarks.md
