"""What the machine has to give: memory available to a new allocation."""

from __future__ import annotations

import os


def available_memory() -> int:
    """Bytes of memory available without swapping (``MemAvailable`` of /proc/meminfo; the
    physical memory where that cannot be read)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
