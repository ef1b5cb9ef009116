"""Small host utilities the driver, the engines and the commands share: printable paths, the
default worker memory limit, process memory from /proc (MB)."""
from __future__ import annotations

import os


def printable(text: str) -> str:
    """``text`` as valid UTF-8 for logs and terminals: bytes of a non-UTF-8 file name (Python's
    surrogate escapes) are written ``\\xNN``."""
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def default_memory_limit_mb(workers: int) -> float:
    """Half the machine's memory divided among the workers, at least 1 GiB each."""
    try:
        import psutil
        total = psutil.virtual_memory().total
    except ImportError:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return max(1024.0, total / 2**20 / 2 / max(1, workers))


def tree_rss_mb() -> float:
    """Resident memory of this process and its children (MB); 0 without psutil."""
    try:
        import psutil
    except ImportError:
        return 0.0
    total = 0
    try:
        me = psutil.Process()
        for p in [me] + me.children(recursive=True):
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
    except psutil.Error:
        return 0.0
    return total / 2**20


def process_memory_mb(pid: int) -> tuple[float, float, float]:
    """(VmRSS, VmHWM, VmData) of a process in MB from /proc; zeros where unavailable. VmHWM is
    the peak of the process' own memory (unlike ``ru_maxrss``, which after fork + exec starts at
    the parent's size)."""
    out = {"VmRSS": 0.0, "VmHWM": 0.0, "VmData": 0.0}
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                key, _, value = line.partition(b":")
                k = key.decode()
                if k in out:
                    out[k] = int(value.split()[0]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return out["VmRSS"], out["VmHWM"], out["VmData"]
