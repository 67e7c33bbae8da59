# SPDX-License-Identifier: Apache-2.0
"""Work around a packaging bug of the ROS 2 PyPI wheels (idempotent).

Their exported CMake targets carry include directories of the machine that built them
(/opt/python/cpXY-cpXY/include/pythonX.Y and .../site-packages/numpy/_core/include);
CMake's generate step then fails with "Imported target ... includes non-existent path".
This rewrites those paths in <prefix>/share/*/cmake/*.cmake to this interpreter's
Python include directory and numpy's include directory.
"""

import glob
import os
import re
import sys
import sysconfig

import numpy

PY_INC = re.compile(r"/opt/python/cp3\d+-cp3\d+/include/python3\.\d+t?")
NP_INC = re.compile(
    r"/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+t?/site-packages/numpy/_?core/include"
)


def main(prefix: str) -> int:
    py_inc = sysconfig.get_paths()["include"]
    np_inc = numpy.get_include()
    changed = 0
    for path in glob.glob(os.path.join(prefix, "share", "*", "cmake", "*.cmake")):
        with open(path, encoding="utf-8") as f:
            text = f.read()
        new = NP_INC.sub(np_inc, PY_INC.sub(py_inc, text))
        if new != text:
            with open(path, "w", encoding="utf-8") as f:
                f.write(new)
            changed += 1
    print(f"fix_ros_wheels_cmake: rewrote {changed} file(s) under {prefix}/share")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else sys.prefix))
