# SPDX-License-Identifier: Apache-2.0
"""``python -m ae_tactile.bagtools``: the ``ae-tactile-replay`` command."""

import sys

from ae_tactile.bagtools.cli import main

if __name__ == "__main__":
    sys.exit(main())
