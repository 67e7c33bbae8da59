# SPDX-License-Identifier: Apache-2.0
"""``--help`` of the node executables: the usage with every parameter a node declares
(`print_help`), and the split of a command line at ``--ros-args``."""

from __future__ import annotations

import importlib

from ae_tactile.ros import params as shared_params
from ae_tactile.ros.params import Param


def _ros_type(value) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "double"
    if isinstance(value, str):
        return "string"
    if isinstance(value, (list, tuple)):
        inner = _ros_type(value[0]) if value else "double"
        return f"{inner}[]"
    return type(value).__name__


def _fmt_default(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt_default(v) for v in value) + "]"
    return str(value)


def format_usage(executable: str, doc: str, params) -> str:
    """Usage text of a node executable: synopsis, description, one entry per parameter;
    ``params`` is a list of (full name, Param)."""
    lines = [f"usage: ros2 run ae_tactile {executable} [-h] "
             "[--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r __ns:=/NS]]", ""]
    if doc:
        lines += [doc.strip(), ""]
    lines.append("parameters (-p NAME:=VALUE, or a --params-file section for this node):")
    for name, p in params:
        rng = ""
        if p.choices:
            rng = "; one of " + ", ".join(map(str, p.choices))
        elif p.lo is not None and p.hi is not None and not isinstance(p.default, bool):
            rng = f"; {_fmt_default(p.lo)} .. {_fmt_default(p.hi)}"
        kind = _ros_type(p.default)
        lines.append(f"  {name} ({kind}, default {_fmt_default(p.default)}{rng})")
        lines.append(f"      {p.description}")
    return "\n".join(lines)


def _resolve(module, source):
    """A parameter table: a list of Param, an attribute name of ``module``, or
    'package.module:attr'; a callable is called. None when it does not exist."""
    if isinstance(source, str):
        mod_name, _, attr = source.rpartition(":")
        try:
            owner = importlib.import_module(mod_name) if mod_name else module
        except ImportError:
            return None
        source = getattr(owner, attr, None)
    if callable(source):
        source = source()
    if isinstance(source, (list, tuple)) and all(isinstance(p, Param) for p in source):
        return list(source)
    return None


def module_params(module, tables=None) -> tuple[list, list[str]]:
    """([(full name, Param)], [tables not found]) of a node module.

    ``tables``: (prefix, source) pairs (see `_resolve`); default: the module's
    ``NODE_PARAMETERS`` if it has one, else its own module-level ``*_PARAMS`` lists."""
    if tables is None:
        tables = getattr(module, "NODE_PARAMETERS", None)
    if tables is None:
        tables = [("", name) for name, value in vars(module).items()
                  if name.endswith("_PARAMS") and _resolve(module, value) is not None
                  and value is not getattr(shared_params, name, None)]
    out, missing = [], []
    for prefix, source in tables:
        table = _resolve(module, source)
        if table is None:
            missing.append(source if isinstance(source, str) else repr(source))
            continue
        out.extend((prefix + p.name, p) for p in table)
    return out, missing


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(arguments before --ros-args, --ros-args and what follows)."""
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []


def wants_help(own_args: list[str]) -> bool:
    """``-h`` or ``--help`` among the arguments before ``--ros-args``."""
    return any(a in ("-h", "--help") for a in own_args)


def print_help(module, executable: str, tables=None) -> None:
    """Print the usage of the node ``module`` (`format_usage`) with every parameter of
    ``tables`` (see `module_params`), falling back to the module's own tables.

    Parameters
    ----------
    module : module
        The node's module (its docstring is the description).
    executable : str
        Name shown in the synopsis.
    tables : list or None
        (prefix, source) pairs of the node's parameters.

    Returns
    -------
    None
    """
    doc = (module.__doc__ or "").strip()
    params, missing = module_params(module, tables)
    if missing:        # the help must work even when a table was renamed
        fallback, _ = module_params(module)
        known = {name for name, _ in params}
        params += [(name, p) for name, p in fallback if name not in known]
    print(format_usage(executable, doc, params), flush=True)
    if missing:
        print(f"\n(parameter tables not found: {', '.join(missing)})", flush=True)
