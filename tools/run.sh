#!/usr/bin/env bash
# SPDX-License-Identifier: Apache-2.0
# tools/run.sh CMD [ARGS...]: set up what is missing (tools/setup.sh), then run CMD with
# the package's environment (venv + colcon install) from the repository root.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/tools/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/tools/env.sh"
cd "$ROOT"
exec "$@"
