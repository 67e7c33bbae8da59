#!/usr/bin/env bash
# Regenerate the README's parameter tables from the nodes' declarations.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
"$ROOT/tools/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/tools/env.sh"
cd /tmp   # not the source tree: the installed package carries ae_tactile.msg
python - "$ROOT/README.md" <<'PY'
import re, sys
from ae_tactile.ros.param_docs import BEGIN, END, markdown
path = sys.argv[1]
text = open(path).read()
new = markdown()
if "PARAMETERS_PLACEHOLDER" in text:
    text = text.replace("PARAMETERS_PLACEHOLDER", new)
else:
    text = re.sub(re.escape(BEGIN) + ".*?" + re.escape(END), lambda m: new, text, flags=re.S)
open(path, "w").write(text)
print("README parameter tables updated")
PY
