"""What machine a benchmark ran on, for the header of its table."""

from __future__ import annotations


def cpu_and_memory() -> tuple[str, str]:
    """The CPU model and the total RAM, from /proc ("unknown ..." where that is not available)."""
    cpu, memory = "unknown CPU", "unknown memory"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        kb = next(int(line.split()[1]) for line in open("/proc/meminfo") if line.startswith("MemTotal"))
        memory = f"{kb / 2**20:.0f} GiB RAM"
    except (OSError, StopIteration):
        pass
    return cpu, memory
