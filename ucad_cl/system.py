"""Small host utilities the driver, the engines and the commands share: printable paths, the
default worker memory limit, process memory from /proc (MB), and ``call_isolated`` (a function
run in a fresh child interpreter)."""
from __future__ import annotations

import importlib
import os
import pickle
import signal
import subprocess
import sys
from multiprocessing.connection import Connection


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


# ----------------------------------------------------------------------------- isolated calls

class IsolatedCallFailed(RuntimeError):
    """The child of ``call_isolated`` gave no answer: ``kind`` is "timeout" (still running after
    the timeout, killed) or "crashed" (died); ``how`` says which signal, exit code or timeout."""

    def __init__(self, kind: str, how: str):
        self.kind, self.how = kind, how
        super().__init__(f"the child process {how}")


def call_isolated(func, *args, timeout: float, clean_exit: bool = False, **kwargs):
    """``func(*args, **kwargs)`` in a fresh child interpreter; its return value, or the exception
    it raised, raised again here.

    Used where a native library may crash or hang on what it is given (mesh loaders), or where
    loading it would stay in this process's memory for good (the build driver checks the
    segmenter and probes the OpenCL devices this way: ~150 MB for PoCL and its LLVM, ~60 MB for
    an onnxruntime session, never freed). ``func`` must be a module-level function; arguments,
    result and exception must pickle (an exception that does not comes back as RuntimeError
    "Type: message"). The child is ``python -c`` (not multiprocessing 'spawn', which re-runs the
    caller's ``__main__`` and breaks scripts without a main guard) with this process's
    ``sys.path`` and environment; the call goes in on stdin, the answer comes back on a dedicated
    pipe (native libraries may write to stdout). ``IsolatedCallFailed`` when the child dies
    without answering or runs past ``timeout`` seconds (then it is killed); with ``clean_exit``,
    also when it answers and then exits abnormally (LLVM aborting at exit, say). ``func`` may be
    given as ``"module:function"``, imported only in the child.
    """
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
    read_fd, write_fd = os.pipe()
    code = ("import pickle, sys; sys.path[:0] = pickle.load(sys.stdin.buffer); "
            "from ucad_cl.system import serve_isolated_call; serve_isolated_call(int(sys.argv[1]))")
    try:
        proc = subprocess.Popen([sys.executable, "-c", code, str(write_fd)], pass_fds=(write_fd,),
                                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
    finally:
        os.close(write_fd)
    conn = Connection(read_fd, writable=False)
    try:
        try:
            assert proc.stdin is not None
            proc.stdin.write(pickle.dumps([p for p in sys.path if isinstance(p, str)]))
            proc.stdin.write(pickle.dumps((func, args, kwargs)))
            proc.stdin.close()
        except BrokenPipeError:
            pass                                    # the child died early: reported below
        if not conn.poll(timeout):
            proc.kill()
            proc.wait()
            raise IsolatedCallFailed("timeout", f"did not finish within {timeout:g} s (killed)")
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            rc = proc.wait()
            how = f"killed by signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
            raise IsolatedCallFailed("crashed", f"died ({how})") from None
    finally:
        conn.close()
        if proc.poll() is None:
            try:
                proc.wait(timeout if clean_exit else 5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    if kind == "raise":
        raise payload
    if kind != "ok":
        raise RuntimeError(payload)
    if clean_exit and proc.returncode != 0:
        rc = proc.returncode
        how = f"killed by signal {signal.Signals(-rc).name}" if rc < 0 else f"exit code {rc}"
        raise IsolatedCallFailed("crashed", f"answered, then died at exit ({how})")
    return payload


def serve_isolated_call(fd: int) -> None:
    """Child side of ``call_isolated``: read (func, args, kwargs) on stdin, answer on ``fd``:
    ("ok", result), ("raise", exception) or ("error", "Type: message")."""
    conn = Connection(fd, readable=False)
    try:
        func, args, kwargs = pickle.load(sys.stdin.buffer)
        if isinstance(func, str):                   # "module:function"
            module, name = func.split(":")
            func = getattr(importlib.import_module(module), name)
        result: tuple = ("ok", func(*args, **kwargs))
    except BaseException as e:  # noqa: BLE001 - everything goes back to the parent
        try:
            pickle.loads(pickle.dumps(e))
            result = ("raise", e)
        except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as text
            result = ("error", f"{type(e).__name__}: {e}")
    try:
        conn.send(result)
    except Exception as e:  # noqa: BLE001 - a result that does not pickle
        conn.send(("error", f"the result of the isolated call does not pickle "
                            f"({type(e).__name__}: {e})"))
    conn.close()
