#!/usr/bin/env bash
# SPDX-License-Identifier: Apache-2.0
# Regenerate README.md's parameter tables and config/{water_skin,silicone}.yaml from the
# nodes' parameter tables (the one place they are defined).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/tools/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/tools/env.sh"
cd /tmp   # not the source tree: the installed package carries ae_tactile.msg
AE_TACTILE_ROOT="$ROOT" python -m ae_tactile.ros.param_docs --write
