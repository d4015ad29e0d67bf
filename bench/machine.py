"""The machine a benchmark ran on, in one line: CPU model (lscpu), cores, the vector width the CPU has
and the one numba generates code for, the load average. Benchmarks print it above their figures.

numba generates code for the host CPU unless NUMBA_CPU_NAME (and NUMBA_CPU_FEATURES) say otherwise; a
laptop-like AVX2 figure on an AVX-512 machine is taken with

    NUMBA_CPU_NAME=haswell NUMBA_CPU_FEATURES="$(python bench/machine.py --haswell-features)" \\
        NUMBA_CACHE_DIR=/tmp/numba-haswell python bench/render.py

(numba keys its cache by CPU name and features, so the separate cache folder only keeps the two builds
from overwriting each other's index.) With NUMBA_CPU_NAME alone numba would still enable the host's
features (AVX-512 included).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys

#: LLVM's features of a Haswell core (AVX2, FMA, no AVX-512), for NUMBA_CPU_FEATURES.
HASWELL_FEATURES = ("+64bit,+avx,+avx2,+bmi,+bmi2,+cmov,+cx16,+cx8,+f16c,+fma,+fsgsbase,+fxsr,+invpcid,"
                    "+lzcnt,+mmx,+movbe,+pclmul,+popcnt,+rdrnd,+sahf,+sse,+sse2,+sse3,+sse4.1,+sse4.2,"
                    "+ssse3,+x87,+xsave,+xsaveopt")


def cpu_model() -> str:
    """lscpu's model name (else /proc/cpuinfo's, else 'unknown CPU')."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        m = re.search(r"^Model name:\s*(.+)$", out, re.M)
        if m:
            return m.group(1).strip()
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        with open("/proc/cpuinfo") as f:
            m = re.search(r"^model name\s*:\s*(.+)$", f.read(), re.M)
        return m.group(1).strip() if m else "unknown CPU"
    except OSError:
        return "unknown CPU"


def host_vector_width() -> str:
    """'AVX-512', 'AVX2' or 'SSE' from the CPU's flags."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = set(re.search(r"^flags\s*:\s*(.+)$", f.read(), re.M).group(1).split())
    except (OSError, AttributeError):
        return "unknown"
    return "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "SSE"


def numba_target() -> str:
    """The CPU numba compiles for and its widest vectors, e.g. 'host (znver4), AVX-512' or
    'haswell (NUMBA_CPU_NAME), AVX2'."""
    name = os.environ.get("NUMBA_CPU_NAME")
    features = os.environ.get("NUMBA_CPU_FEATURES")
    if name is None:
        import llvmlite.binding as ll
        width = host_vector_width() if features is None else _width_of(features)
        return f"host ({ll.get_host_cpu_name()}), {width}"
    width = _width_of(features) if features is not None else host_vector_width() + " (host features!)"
    return f"{name} (NUMBA_CPU_NAME), {width}"


def _width_of(features: str) -> str:
    on = {f[1:] for f in features.split(",") if f.startswith("+")}
    return "AVX-512" if "avx512f" in on else "AVX2" if "avx2" in on else "SSE"


def describe() -> str:
    """One line about this machine for a benchmark's header."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"CPU: {cpu_model()}, {os.cpu_count()} cores, {host_vector_width()}; numba code for "
            f"{numba_target()}; load average {load:.2f}")


if __name__ == "__main__":
    print(HASWELL_FEATURES if sys.argv[1:] == ["--haswell-features"] else describe())
