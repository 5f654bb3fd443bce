#!/usr/bin/env bash
# Regenerate all recordings, clean signals and truth.json (deterministic, seeded).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
cd "$here"
rm -rf recs clean truth.json
python3 sim.py "$here"
python3 validate.py "$here"
