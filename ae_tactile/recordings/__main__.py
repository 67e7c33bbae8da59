# SPDX-License-Identifier: Apache-2.0
"""``python -m ae_tactile.recordings FILE ...``: the ``ae-tactile-detect`` command."""

import sys

from ae_tactile.recordings.cli import main

if __name__ == "__main__":
    sys.exit(main())
