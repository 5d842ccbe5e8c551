"""Writing benchmark results into docs/PERFORMANCE.md, one section per benchmark, machine and date included.

Each benchmark calls ``write_section(name, title, markdown_body)``; the section is delimited by HTML comments
so that re-running one benchmark replaces only its own section and leaves the others as they were. Also the
figures every benchmark reports the same way: ``percentile`` (nearest rank) and ``load_average``.
"""

import datetime
import math
import os
import platform
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PERFORMANCE_MD = os.path.join(ROOT, "docs", "PERFORMANCE.md")
HEADER = ("# Performance\n\nWritten by the benchmarks in `bench/` (`make bench` runs them all, `make bench-NAME` one "
          "of them). Each section says the machine and the date it was measured on; targets are the ones the "
          "platform is built to meet.\n")


def percentile(values, fraction):
    """The nearest-rank percentile of ``values`` (``fraction`` 0.5 for p50, 0.99 for p99): a value measured."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(fraction * len(ordered)) - 1)]


def load_average():
    """The 1- and 5-minute load averages as "A / B" ("?" when /proc/loadavg cannot be read)."""
    try:
        with open("/proc/loadavg") as f:
            return " / ".join(f.read().split()[:2])
    except OSError:
        return "?"


def machine_description():
    """One line naming this machine: CPU model, core count, memory, OS, kernel, Python."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gib = ""
    try:
        with open("/proc/meminfo") as f:
            kib = int(f.readline().split()[1])
            mem_gib = f", {kib / 1024 / 1024:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    os_name = platform.platform()
    try:
        with open("/etc/os-release") as f:
            fields = dict(line.rstrip().split("=", 1) for line in f if "=" in line)
            os_name = fields.get("PRETTY_NAME", os_name).strip('"')
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores{mem_gib}; {os_name}, kernel {platform.release()}; "
            f"Python {platform.python_version()}")


def write_section(name, title, body, path=PERFORMANCE_MD):
    """Replace (or add) the section ``name`` of docs/PERFORMANCE.md with ``title`` and ``body``."""
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    section = (f"<!-- bench:{name} -->\n## {title}\n\nMeasured {stamp} on {machine_description()}.\n\n"
               f"{body.strip()}\n<!-- /bench:{name} -->")
    text = HEADER
    if os.path.exists(path):
        with open(path) as f:
            text = f.read()
    pattern = re.compile(rf"<!-- bench:{re.escape(name)} -->.*?<!-- /bench:{re.escape(name)} -->", re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: section, text)
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(text if text.endswith("\n") else text + "\n")
    return path
