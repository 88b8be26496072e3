"""Message definitions and type hashes of installed ROS 2 message types (no ROS import).

rosbag2 stores, per topic, the schema encoding ``ros2msg``: the ``.msg`` text of the type
followed by every dependency, each preceded by a line of 80 ``=`` and ``MSG: pkg/Name``. The
text comes from ``share/<pkg>/msg/<Name>.msg`` next to the installed interfaces (the venv's
``share/`` or an ``AMENT_PREFIX_PATH`` entry); the RIHS01 type hash from ``<Name>.json``.
"""

from __future__ import annotations

import functools
import json
import os
import re
import sys
from pathlib import Path
from typing import Optional

from ..core.types import InputError

SEPARATOR = "=" * 80
PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
              "int32", "uint32", "int64", "uint64", "string", "wstring"}
_BOUND = re.compile(r"(\[[^\]]*\])$|(<=\d+)$")


def _share_dirs() -> list[Path]:
    """Folders that may contain ``<pkg>/msg/*.msg`` (venv first, then the ament prefixes)."""
    dirs = [Path(sys.prefix) / "share"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / "share")
    return [d for d in dirs if d.is_dir()]


def split_type(type_name: str) -> tuple[str, str]:
    """("sensor_msgs", "Image") for "sensor_msgs/msg/Image" or "sensor_msgs/Image"."""
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise InputError(f"message type {type_name!r} is not of the form pkg/msg/Name")


def _find(pkg: str, name: str, suffix: str) -> Optional[Path]:
    for d in _share_dirs():
        p = d / pkg / "msg" / f"{name}{suffix}"
        if p.is_file():
            return p
    return None


@functools.lru_cache(maxsize=None)
def msg_text(type_name: str) -> Optional[str]:
    """The ``.msg`` file text of a type, or None when it is not installed."""
    pkg, name = split_type(type_name)
    p = _find(pkg, name, ".msg")
    return p.read_text(encoding="utf-8") if p else None


def _dependencies(pkg: str, text: str) -> list[str]:
    """Non-primitive field types of a ``.msg`` text as "pkg/Name", in order of appearance."""
    deps: list[str] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2 or "=" in parts[1] or "=" in parts[0]:
            continue  # constants are primitive
        ftype = parts[0]
        while True:
            m = _BOUND.search(ftype)
            if not m:
                break
            ftype = ftype[:m.start()]
        if ftype in PRIMITIVES:
            continue
        if ftype == "Header":
            ftype = "std_msgs/Header"
        elif "/" not in ftype:
            ftype = f"{pkg}/{ftype}"
        else:
            ftype = "/".join(split_type(ftype))
        if ftype not in deps:
            deps.append(ftype)
    return deps


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> Optional[str]:
    """rosbag2's concatenated ``ros2msg`` definition, or None when the type is not installed.

    Dependencies are listed once each, breadth first, as rosbag2's local definition source does.
    """
    text = msg_text(type_name)
    if text is None:
        return None
    pkg, _ = split_type(type_name)
    out = text
    seen = {"/".join(split_type(type_name))}
    queue = _dependencies(pkg, text)
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dtext = msg_text(dep)
        if dtext is None:
            return None  # an incomplete definition would mislead a decoder
        out += f"\n{SEPARATOR}\nMSG: {dep}\n{dtext}"
        queue.extend(d for d in _dependencies(dep.split("/")[0], dtext) if d not in seen)
    return out


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> Optional[str]:
    """The RIHS01 type description hash of an installed type (from its ``.json``), else None."""
    pkg, name = split_type(type_name)
    p = _find(pkg, name, ".json")
    if p is None:
        return None
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    full = f"{pkg}/msg/{name}"
    for h in data.get("type_hashes", []):
        if h.get("type_name") == full:
            return h.get("hash_string")
    return None
